"""The one skip rule of the tests that render LIBERO scenes: the libero extra is optional."""

import pytest

from bench.sim import env as sim_env

needs_libero = pytest.mark.skipif(not sim_env.libero_available(),
                                  reason="libero extra not installed (bash scripts/install_libero.sh)")
