"""`pytest bench ...` inside the test process: the user's command without a fresh interpreter (no
second torch import), and the tiny world (suites, released policies, encoders) loaded once per
test session and lent to every run (tests/worlds.py). `shared=False` runs build their workspace
as a user's run does (torch threads chosen and printed).

A run is `pytest.main` with its terminal in a string: a nested session of its own (its own
config, plugins and GraftSession), importing into this process as a user's run would. No
snapshot of sys.modules is taken and restored, as pytester's is: a module first imported inside
a run stays (re-importing pandas or `datasets` after they were dropped fails).

Tests that need a fresh interpreter (a killed process, xdist workers, submitit tasks, the hub
world that huggingface_hub reads at import) keep their subprocess.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass

import pytest
import torch

from bench.plugin import SESSION_KEY
from ondisk.paths import REPO_ROOT
from tests.worlds import lent_workspace


# A run in this process stays in it: without -n a tiny-world run would start two xdist workers
# (bench.scheduling.default_workers), fresh interpreters the lent world cannot reach.
ONE_PROCESS = ("-n", "0")


@dataclass(frozen=True)
class BenchRun:
    """What a `pytest bench` run gave: its exit code and its terminal output."""

    returncode: int
    stdout: str
    stderr: str


def lent(session):
    """The session's workspace, lending the loaded parts of its world (tests/worlds.py)."""
    return lent_workspace(session.profile, session.store, progress=session.progress_sink(),
                          rollouts=session.rollouts, feature_dtype=session.feature_dtype)


def report_without_figures(results_dir, path, extra_sections=()):
    """The session's report, its PNG figures left out (`python -m bench.report --no-plots`)."""
    from bench.report.build import build_report

    return build_report(results_dir, path, extra_sections=list(extra_sections), plots=False)


class _LendWorkspace:
    def __init__(self, figures: bool) -> None:
        self.figures = figures

    @pytest.hookimpl(trylast=True)  # after bench.plugin built the session
    def pytest_configure(self, config):
        session = config.stash[SESSION_KEY]
        session.use_seams(workspace_factory=lent)
        if not self.figures:
            session.use_seams(report_builder=report_without_figures)


class _NoGcAtExit:
    """What pytester's inline runs do: no forced garbage collection when the run ends. pytest's
    unraisable-exception plugin runs a full gc.collect() at unconfigure: over this process's
    heap (torch, LeRobot, the loaded world) ~2 s a run (measured: a resumed 3-cell run 2.5 s
    -> 0.34 s). The test session around the runs still collects and reports what is
    unraisable."""

    @staticmethod
    def pytest_configure(config):
        from _pytest.unraisableexception import gc_collect_iterations_key

        config.stash[gc_collect_iterations_key] = 0


def run_bench(*args: str, shared: bool = True, figures: bool = False,
              env: dict[str, str | None] | None = None, plugins: tuple = ()) -> BenchRun:
    """`pytest bench -p no:cacheprovider *args` in this process; `env` sets (None: unsets)
    variables for the run. Torch's thread count is restored afterwards. Shared runs draw the
    report's figures only with `figures=True` (~1.2 s a report; the figures have their own
    tests in test_report and the screen modules, and the ~30 in-process runs check text);
    `plugins`: more plugin objects for the run (a test's look inside it)."""
    threads = torch.get_num_threads()
    plugins = [_NoGcAtExit(), *([_LendWorkspace(figures)] if shared else []), *plugins]
    out, err = io.StringIO(), io.StringIO()
    with pytest.MonkeyPatch.context() as patch:
        for name, value in (env or {}).items():
            if value is None:
                patch.delenv(name, raising=False)
            else:
                patch.setenv(name, value)
        patch.chdir(REPO_ROOT)
        try:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                code = pytest.main([str(REPO_ROOT / "bench"), "-p", "no:cacheprovider",
                                    "--capture=sys", *ONE_PROCESS, *args], plugins=plugins)
        finally:
            torch.set_num_threads(threads)
    return BenchRun(int(code), out.getvalue(), err.getvalue())


@pytest.fixture
def bench_run(pytester):
    """`pytest bench ARGS` through pytester in this process (a module using it declares
    `pytest_plugins = ["pytester"]`), with a private results folder and report: each run's
    `.screen` is its stdout and stderr joined, `.records` the cell files it wrote; `bench_run.path`
    is the folder."""
    def run(*args: str):
        out = pytester.runpytest_inprocess(
            str(REPO_ROOT / "bench"), "-p", "no:cacheprovider", *ONE_PROCESS, "--results-dir",
            str(pytester.path / "results"), "--report", str(pytester.path / "REPORT.md"), *args)
        out.screen = "\n".join(out.outlines + out.errlines)
        out.records = sorted((pytester.path / "results").glob("cells/*.json"))
        return out

    run.path = pytester.path
    return run
