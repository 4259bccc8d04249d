"""graftbench: `pytest bench` runs the grid; `pytest tests` the harness's own tests.

The offline switch is set here, at import, before anything imports huggingface_hub: in the
offline world an accidental hub call then fails at once instead of retrying for ~50 s.
"""

import os
import sys


def _option_from_argv(argv: list[str], option: str) -> str | None:
    for i, arg in enumerate(argv):
        if arg == option and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith(option + "="):
            return arg.split("=", 1)[1]
    return None


def _profile_from_argv(argv: list[str]) -> str:
    """--profile, else the `profile` of the --grid file (bench.grid.gridfile), else tiny."""
    profile = _option_from_argv(argv, "--profile")
    grid = _option_from_argv(argv, "--grid")
    if profile is None and grid is not None:
        from bench.grid.gridfile import base_profile_of

        profile = base_profile_of(grid)
    return profile or "tiny"


if _profile_from_argv(sys.argv) != "paper":
    for _var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
        os.environ[_var] = "1"

pytest_plugins = ["bench.plugin"]
