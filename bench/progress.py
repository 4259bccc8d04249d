"""Progress you can see under plain `pytest bench`: lines through pytest's terminal reporter with
capture suspended (what pytest-benchmark does), one line per long phase every `every_s` seconds
with an estimate of time left. Silent under -q, GRAFTBENCH_QUIET=1 and in xdist workers.

`progress` arguments across bench/ take a sink (`ProgressSink`): `STDERR` (outside pytest: stderr,
when it is a terminal), a `TerminalSink` (inside pytest), or `QUIET` (the null sink).
"""

from __future__ import annotations

import os
import sys
import time
from typing import Protocol


class ProgressSink(Protocol):
    def line(self, text: str) -> None: ...


class NullSink:
    """Says nothing: the sink of quiet work (-q, xdist workers, array tasks, tests)."""

    def line(self, text: str) -> None:
        pass


class StderrSink:
    """Outside pytest (python -m ..., scripts): stderr, only when it is a terminal."""

    def line(self, text: str) -> None:
        if sys.stderr.isatty():
            sys.stderr.write(text + "\n")
            sys.stderr.flush()


class TerminalSink:
    """Inside pytest: the terminal reporter, with output capture suspended for the line."""

    def __init__(self, config) -> None:
        self.reporter = config.pluginmanager.get_plugin("terminalreporter")
        self.capman = config.pluginmanager.get_plugin("capturemanager")

    def line(self, text: str) -> None:
        if self.reporter is None:
            return
        if self.capman is None:
            self.reporter.write_line(text)
            return
        with self.capman.global_and_fixture_disabled():
            self.reporter.write_line(text)


QUIET = NullSink()
STDERR = StderrSink()


def as_sink(progress) -> ProgressSink | None:
    """The sink of a `progress` argument; None when quiet (the null sink, None,
    GRAFTBENCH_QUIET=1). A bool is the older form (True: STDERR, False: QUIET)."""
    if progress is True:
        progress = STDERR
    if os.environ.get("GRAFTBENCH_QUIET") == "1" or not progress or isinstance(progress, NullSink):
        return None
    return progress


def say(progress, text: str) -> None:
    """One line to the sink of `progress` (nothing when quiet)."""
    sink = as_sink(progress)
    if sink is not None:
        sink.line(f"[graftbench] {text}")


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60}m{seconds % 60:02d}s" if seconds >= 60 else f"{seconds}s"


class Progress:
    """`label: done/total` lines at most every `every_s` seconds (and when done, if any line was
    written or the work took that long), each with elapsed time and time left at the mean rate."""

    def __init__(self, label: str, total: int, progress, every_s: float = 30.0) -> None:
        self.label, self.total, self.every_s = label, total, every_s
        self.sink = as_sink(progress)
        self.start = self._last = time.monotonic()
        self.lines = 0

    def update(self, done: int, note: str = "") -> None:
        if self.sink is None:
            return
        now = time.monotonic()
        finished = done >= self.total
        if now - self._last < self.every_s and not (finished and self.lines):
            return
        self._last = now
        elapsed = now - self.start
        left = elapsed / max(done, 1) * (self.total - done)
        eta = "done" if finished else f"~{_clock(left)} left"
        self.sink.line(f"[graftbench]   {self.label}: {done}/{self.total} {note} "
                       f"({_clock(elapsed)}, {eta})".replace("  (", " ("))
        self.lines += 1
