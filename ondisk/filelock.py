"""One exclusive file lock for processes sharing a cache or results dir (xdist workers, job-array
tasks): the release cache, the feature store and the results store all wait on it."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path


@contextlib.contextmanager
def _lock_fd(lock_file: Path):
    """An open descriptor on `lock_file` (created, with its folder), closed after the block:
    closing it releases any flock taken on it."""
    lock_file = Path(lock_file)
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        yield fd
    finally:
        os.close(fd)


def _lock_now(fd: int) -> bool:
    """Take the exclusive flock if free (True), else leave it (False), without waiting."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True


@contextlib.contextmanager
def exclusive(lock_file: Path, on_wait=None):
    """An exclusive flock on `lock_file` (created, with its folder) for the block; the kernel
    releases it if the process dies. `on_wait()` is called once, before waiting, when another
    process holds it."""
    with _lock_fd(lock_file) as fd:
        if not _lock_now(fd):
            if on_wait is not None:
                on_wait()
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield


@contextlib.contextmanager
def try_exclusive(lock_file: Path):
    """`exclusive` without waiting: yields True holding the lock, or False at once (and holds
    nothing) when another process holds it. For work that can simply be left to its holder."""
    with _lock_fd(lock_file) as fd:
        yield _lock_now(fd)
