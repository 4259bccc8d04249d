"""Where graftbench keeps generated data, caches and results (all outside git)."""

from __future__ import annotations

import os
import shutil
import tempfile
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


def not_a_folder(path: Path) -> str | None:
    """Why `path` cannot be (or become) a writable folder, or None. Creates nothing: the first
    ancestor that exists must be a writable folder."""
    if path.exists():
        if not path.is_dir():
            return "a file, not a folder"
        return None if os.access(path, os.W_OK | os.X_OK) else "not writable"
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                return f"{parent} is a file, so no folder can be made there"
            return None if os.access(parent, os.W_OK | os.X_OK) else f"{parent} is not writable"
    return None


def unwritable(folder: Path) -> str | None:
    """Why `folder` cannot be made and written, or None once it is made and a probe file was
    written there: the check that a run's output folder will take its files, made before any
    work (os.access says yes to root on a read-only mount; a write says no)."""
    problem = not_a_folder(folder)
    if problem:
        return problem
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-probe-"):
            pass
    except OSError as e:
        return f"not writable ({e.strerror or e})"
    return None
