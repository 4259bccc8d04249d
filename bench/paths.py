"""Where graftbench keeps generated data, caches and results (all outside git)."""

from __future__ import annotations

import os
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent


def cache_dir() -> Path:
    """Generated suites, tiny checkpoints, feature caches. Override with GRAFTBENCH_CACHE."""
    path = Path(os.environ.get("GRAFTBENCH_CACHE", REPO_ROOT / ".graftbench" / "cache"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def default_results_dir() -> Path:
    return REPO_ROOT / ".graftbench" / "results"
