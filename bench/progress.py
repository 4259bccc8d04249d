"""Progress you can see under plain `pytest bench`: lines through pytest's terminal reporter with
capture suspended (what pytest-benchmark does), one line per long phase every `every_s` seconds
with an estimate of time left. Silent under -q and GRAFTBENCH_QUIET=1.

`progress` arguments across bench/ take a sink (`ProgressSink`): `STDERR` (outside pytest: stderr,
when it is a terminal), a `TerminalSink` (inside pytest), a `WorkerSink` (an xdist worker: the
user's terminal, which the worker's stderr still is), a `LogSink` (a job array task: its log), or
`QUIET` (the null sink). Wherever a session calls in, `progress` is a required argument (no
default sink: tests/test_progress_sinks.py checks the signatures), so a long step cannot fall
silent by forgetting it, as the sim suite's demonstrations once did (ten silent minutes).
"""

from __future__ import annotations

import os
import sys
import time
from typing import Protocol, TextIO


class ProgressSink(Protocol):
    def line(self, text: str) -> None: ...


class NullSink:
    """Says nothing: the sink of quiet work (-q, GRAFTBENCH_QUIET=1, tests)."""

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
            return self._write(text)
        with self.capman.global_and_fixture_disabled():
            self._write(text)

    def _write(self, text: str) -> None:
        self.reporter.write_line(text)
        self.reporter.flush()  # piped (`| tee run.log`, a batch job's log): now, not at exit


class WorkerSink:
    """An xdist worker: its stderr is the controller's (execnet keeps fd 2), so with the worker's
    capture suspended a line reaches the user's terminal, named by the worker ("[gw0] ...")."""

    def __init__(self, config, worker: str) -> None:
        self.capman = config.pluginmanager.get_plugin("capturemanager")
        self.worker = worker

    def line(self, text: str) -> None:
        if self.capman is None:
            return _write(sys.stderr, f"[{self.worker}] {text}")
        with self.capman.global_and_fixture_disabled():
            _write(sys.stderr, f"[{self.worker}] {text}")


class LogSink:
    """A job array task: every line to its stderr (the task's log file, not a terminal), with
    the wall-clock time, since a log is read after the fact."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream

    def line(self, text: str) -> None:
        _write(self.stream or sys.stderr, f"{time.strftime('%H:%M:%S')} {text}")


def _write(stream: TextIO, text: str) -> None:
    stream.write(text + "\n")  # one write per line: lines from two processes never interleave
    stream.flush()


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


clock = time.monotonic  # the progress lines' clock (a test moves this one, not time's own)


def countdown(start: float, done: int, total: int, already: int = 0) -> str:
    """`done/total, ~T left`: the time left at this process's mean rate since `start`
    (`clock()`); `already`: what was done before it (resumed work, not timed)."""
    ran = done - already
    if done >= total or ran <= 0:  # nothing timed yet: no estimate rather than a wrong one
        return f"{done}/{total}"
    left = (clock() - start) / ran * (total - done)
    return f"{done}/{total}, ~{_clock(left)} left"


class Progress:
    """`label: done/total` lines at most every `every_s` seconds (and when done, if any line was
    written or the work took that long), each with elapsed time and time left at the mean rate."""

    def __init__(self, label: str, total: int, progress, every_s: float = 30.0) -> None:
        self.label, self.total, self.every_s = label, total, every_s
        self.sink = as_sink(progress)
        self.start = self._last = clock()
        self.lines = 0

    def update(self, done: int, note: str = "") -> None:
        if self.sink is None:
            return
        now = clock()
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
