"""graftbench: `pytest bench` runs the grid; `pytest tests` the harness's own tests.

The offline switch is set here, at import, before anything imports huggingface_hub: in the
offline world an accidental hub call then fails at once instead of retrying for ~50 s.
"""

import os
import sys


def _profile_from_argv(argv: list[str]) -> str:
    for i, arg in enumerate(argv):
        if arg == "--profile" and i + 1 < len(argv):
            return argv[i + 1]
        if arg.startswith("--profile="):
            return arg.split("=", 1)[1]
    return "tiny"


if _profile_from_argv(sys.argv) != "paper":
    for _var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
        os.environ[_var] = "1"

pytest_plugins = ["bench.plugin"]
