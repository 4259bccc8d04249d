"""No long step falls silent. Where a session calls in, `progress` is a required
argument (no default sink to forget it on); an xdist worker's and a job array task's lines are
written, not dropped; the shared countdown says how far and how long is left."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from types import SimpleNamespace

import pytest

from bench.progress import LogSink, WorkerSink, countdown, say
from ondisk.paths import REPO_ROOT

# Defaults that mean "report to stderr", captured by pytest until the test ends.
STDERR_DEFAULTS = ("STDERR", "StderrSink()", "True")


def _progress_defaults(path: Path) -> list[str]:
    """`file:function` (or `file:Class.field`) whose `progress` defaults to a stderr sink."""
    found, rel = [], path.relative_to(REPO_ROOT).as_posix()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = node.args
            positional = args.posonlyargs + args.args
            pairs = list(zip(positional[len(positional) - len(args.defaults):], args.defaults))
            pairs += [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]
            found += [f"{rel}:{node.name}" for a, d in pairs
                      if a.arg == "progress" and ast.unparse(d) in STDERR_DEFAULTS]
        elif isinstance(node, ast.ClassDef):  # dataclass fields (the Workspace's)
            found += [f"{rel}:{node.name}.progress" for item in node.body
                      if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name)
                      and item.target.id == "progress" and item.value is not None
                      and ast.unparse(item.value) in STDERR_DEFAULTS]
    return found


def test_no_function_in_bench_defaults_its_progress_to_stderr():
    """The sink is required wherever a session can call in: the sim suite's ten silent minutes
    came from one call that left it out and got stderr. Command-line entry points pass STDERR."""
    found = [hit for path in sorted((REPO_ROOT / "bench").rglob("*.py"))
             for hit in _progress_defaults(path)]
    assert found == []


def test_the_structure_check_sees_a_default(tmp_path, monkeypatch):
    monkeypatch.setattr("tests.test_progress_sinks.REPO_ROOT", tmp_path)
    (tmp_path / "m.py").write_text("def f(x, progress=STDERR): ...\n"
                                   "def g(*, progress: ProgressSink = STDERR, y=1): ...\n"
                                   "def h(progress: ProgressSink, y=STDERR): ...\n"
                                   "class W:\n    progress: ProgressSink = STDERR\n")
    assert _progress_defaults(tmp_path / "m.py") == ["m.py:f", "m.py:g", "m.py:W.progress"]


def test_an_xdist_worker_writes_its_lines_named(monkeypatch, capsys):
    """`-n 2` was silent: workers got the null sink. A worker's stderr is the controller's
    terminal (execnet keeps fd 2); its lines carry the worker's name."""
    from bench.session import GraftSession

    monkeypatch.delenv("GRAFTBENCH_QUIET", raising=False)
    plugins = SimpleNamespace(get_plugin=lambda name: None)
    config = SimpleNamespace(get_verbosity=lambda: 0, workerinput={"workerid": "gw1"},
                             pluginmanager=plugins)
    sink = GraftSession.progress_sink(SimpleNamespace(config=config))
    assert isinstance(sink, WorkerSink)
    say(sink, "training the tiny released pi05 natively")
    assert capsys.readouterr().err == ("[gw1] [graftbench] training the tiny released pi05 "
                                       "natively\n")
    quiet = SimpleNamespace(config=SimpleNamespace(**{**vars(config), "get_verbosity": lambda: -1}))
    say(GraftSession.progress_sink(quiet), "x")  # -q: still quiet
    assert capsys.readouterr().err == ""


def test_a_job_array_task_reports_to_its_log(tmp_path, monkeypatch, capsys):
    """An array task wrote nothing to its log (the null sink, and GRAFTBENCH_QUIET set by the
    task itself): now each line, time-stamped, to its stderr (submitit's <job>_log.err)."""
    from bench.grid.cells import CellSpec
    from bench.grid.kinds import GRAFT
    from bench.grid.protocol import TINY
    from bench.cell import executors, service

    def spy(self, cell):
        say(self.workspace().progress, f"cell {cell.id}: measuring")
        return "record"

    monkeypatch.setattr(service.CellService, "run", spy)
    monkeypatch.delenv("GRAFTBENCH_QUIET", raising=False)
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "cache"))  # the task sets it
    cell = CellSpec(GRAFT, "smolvla", "spatial", 0, "pixels")
    job = executors.CellJob(cell, TINY, str(tmp_path / "results"), str(tmp_path / "cache"))
    assert executors.run_cell_job(job) == "record"
    assert re.fullmatch(rf"\d\d:\d\d:\d\d \[graftbench\] cell {cell.id}: measuring\n",
                        capsys.readouterr().err)


def test_log_sink_writes_whole_time_stamped_lines(tmp_path):
    with (tmp_path / "log").open("w") as stream:
        LogSink(stream).line("a")
        LogSink(stream).line("b")
    assert re.fullmatch(r"\d\d:\d\d:\d\d a\n\d\d:\d\d:\d\d b\n", (tmp_path / "log").read_text())


@pytest.mark.parametrize("done, total, already, elapsed, text", [
    (3, 12, 0, 30.0, "3/12, ~1m30s left"),  # 10 s each, 9 to go
    (5, 12, 3, 20.0, "5/12, ~1m10s left"),  # resumed 3 are not timed: 2 in 20 s, 7 to go
    (3, 12, 3, 20.0, "3/12"),  # nothing timed yet: no estimate
    (12, 12, 0, 99.0, "12/12"),
])
def test_countdown_estimates_at_this_runs_mean_rate(monkeypatch, done, total, already, elapsed,
                                                     text):
    monkeypatch.setattr("bench.progress.clock", lambda: 100.0 + elapsed)
    assert countdown(100.0, done, total, already) == text


def test_a_tiny_suite_reports_the_episodes_it_wrote(tmp_path, monkeypatch):
    """A fresh clone's first step: generating the tiny suites (56 s each on 2 busy cores, no
    line). A clock that moves 31 s per reading shows every update: episodes written of 4 (the
    writer asks for the next episode once it wrote the last; stood in: no LeRobot import)."""
    import itertools

    from bench.suites import synthetic

    clock = itertools.count(0.0, 31.0)
    monkeypatch.setattr("bench.progress.clock", lambda: next(clock))
    monkeypatch.delenv("GRAFTBENCH_QUIET", raising=False)
    lines: list[str] = []

    def write(root, repo_id, features, robot, fps, episodes):  # LeRobot's writer, stood in
        Path(root).mkdir()
        for _, frames in episodes:
            list(frames)

    monkeypatch.setattr(synthetic, "write_dataset", write)
    synthetic.generate_suite("spatial", tmp_path / "suite", seed=0,
                             progress=SimpleNamespace(line=lines.append),
                             episodes_per_task=1, min_len=6, max_len=8)
    assert [re.sub(r" \(.*", "", line) for line in lines] == [
        f"[graftbench]   suite spatial: generating: {k}/4 episodes" for k in (0, 1, 2, 3, 4)]
    assert lines[1].endswith("(1m02s, ~3m06s left)")  # 2 readings after the start: 62 s for 1
