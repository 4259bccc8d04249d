"""Where graftbench keeps generated data, caches and results (all outside git)."""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path
from typing import Callable

REPO_ROOT = Path(__file__).resolve().parent.parent


def cache_dir() -> Path:
    """Generated suites, tiny checkpoints, feature caches. Override with GRAFTBENCH_CACHE."""
    path = Path(os.environ.get("GRAFTBENCH_CACHE", REPO_ROOT / ".graftbench" / "cache"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def build_dataset_dir(final: Path, build: Callable[[Path], object]) -> Path:
    """`build(tmp)` writes a dataset folder into a private temp folder beside `final`, which is
    then renamed to `final`: a crash never leaves a half dataset there, and when another
    process finished first its folder is kept. Returns `final`."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.parent / f".tmp-{final.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        build(tmp)
        try:
            os.rename(tmp, final)
        except OSError:  # another process finished first: keep theirs
            if not (final / "meta" / "info.json").is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final
