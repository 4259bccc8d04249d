"""One exclusive file lock for processes sharing a cache or results dir (xdist workers, job-array
tasks): the release cache, the feature store and the results store all wait on it."""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path


@contextlib.contextmanager
def exclusive(lock_file: Path, on_wait=None):
    """An exclusive flock on `lock_file` (created, with its folder) for the block; the kernel
    releases it if the process dies. `on_wait()` is called once, before waiting, when another
    process holds it."""
    lock_file = Path(lock_file)
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if on_wait is not None:
                on_wait()
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


@contextlib.contextmanager
def try_exclusive(lock_file: Path):
    """`exclusive` without waiting: yields True holding the lock, or False at once (and holds
    nothing) when another process holds it. For work that can simply be left to its holder."""
    lock_file = Path(lock_file)
    lock_file.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            held = False
        else:
            held = True
        yield held
    finally:
        os.close(fd)
