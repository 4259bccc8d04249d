"""One pytest run of the grid: `GraftSession` holds the profile, the results store, the
workspace, the baseline work (save / compare / fail, bench.regression.run) and what ran.

bench.plugin's hooks only hand work on to it. Its seams are public attributes, set before the
first cell runs: `cell_runner(cell, workspace, context) -> CellResult` (bench.run.runner.measure, with the context
the cell's plan gave: bench.run.plan),
`workspace_factory(session) -> workspace`, `report_builder(results_dir, path, extra_sections=)`
(bench.report.build_report). Tests replace those, never private state.
"""

from __future__ import annotations

import os
import sys
from dataclasses import replace
from pathlib import Path
from typing import Callable

import pytest

from bench.grid.cells import CellSpec
from bench.options import parse_options
from bench.startup import check_startup, check_writable, collects_grid, offline_env
from bench.progress import say
from bench.regression.run import BaselineRun


def _unavailable_errors() -> tuple[type, ...]:
    """Errors that mean "an artifact is missing" and carry their own one-line fix."""
    from backbones.base import BackboneUnavailable
    from bench.suites.base import SuiteUnavailable
    from encoders.registry import EncoderUnavailable

    return (BackboneUnavailable, SuiteUnavailable, EncoderUnavailable)


def _run_cell(cell, ws, context):
    from bench.run.runner import measure

    return measure(cell, ws, context)


def _build_report(results_dir, path, extra_sections=()):
    from bench.report.build import build_report

    return build_report(results_dir, path, extra_sections=list(extra_sections))


class GraftSession:
    """State of one pytest run of the grid: profile, store, workspace, baseline, what ran."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        # Start-up: every option, parsed once into a frozen value before collection
        # (bench.options): a bad one is ONE UsageError screen, exit 4, no cell run.
        self.options = options = parse_options(config)
        self.startup_lines = list(options.startup_lines)  # printed at the session's start
        offline_env(self.profile.offline)
        # Seams (module docstring).
        self.cell_runner: Callable = _run_cell
        self.workspace_factory: Callable = _default_workspace
        self.report_builder: Callable = _build_report
        self.baseline = BaselineRun(options.baseline, self.profile.protocol.hash)
        self._workspace = None
        self._store = None
        self.outcomes: dict[str, str] = {}  # cell id -> "measured" | "resumed" | failure line
        self.records: dict = {}  # cell id -> the Record this run measured or resumed
        self.selected: list[str] = []
        self.screens_selected: list[str] = []  # test_screen cases collected (screen ids)
        self.robust_selected: list[str] = []  # test_robust cases collected (cell ids)
        self._robustness = None
        self._screening = None
        self.report_written: Path | None = None
        self.report_error: str | None = None  # why REPORT.md could not be written, if it failed
        self.set_aside_lines: list[str] = []  # unreadable records moved aside (store.set_aside)
        self._cell_array = None  # bench.run.executors.CellArray, when --executor is not local
        # Names, user paths, output folders: checked here when this run collects the grid (an
        # xdist worker's controller checked them); else at collection (bench.plugin).
        self.names_checked = collects_grid(config) and not hasattr(config, "workerinput")
        if self.names_checked:
            self.startup_lines += check_startup(self.profile, options.labels)
            self.store  # opens (creates, probes) the results dir
            check_writable("--report", self.report_path.parent)

    # What the options say, by the names the cells' code reads (one value: self.options).
    profile = property(lambda self: self.options.profile)
    results_dir = property(lambda self: self.options.results_dir)
    report_path = property(lambda self: self.options.report_path)
    rerun = property(lambda self: self.options.rerun)
    rollouts = property(lambda self: self.options.rollouts)
    rollout_batch = property(lambda self: (self.options.rollout_batch, self.options.rollout_envs))
    features_mode = property(lambda self: self.options.features_mode)
    feature_dtype = property(lambda self: self.options.feature_dtype)
    screen_options = property(lambda self: self.options.screen)  # None without --screen

    @property
    def store(self):
        from bench.results.store import ResultsDirError, ResultStore

        if self._store is None:
            try:  # first opened at collection: a UsageError there, never an INTERNALERROR
                self._store = ResultStore(self.results_dir)
            except ResultsDirError as e:
                raise pytest.UsageError(f"--results-dir: {e}") from None
        return self._store

    def workspace(self):
        if self._workspace is None:
            self._workspace = self.workspace_factory(self)
        return self._workspace

    def progress_sink(self):
        """The terminal, or False: under -q, GRAFTBENCH_QUIET=1 and in xdist workers (their
        output would interleave with the controller's)."""
        from bench.progress import TerminalSink

        quiet = self.config.get_verbosity() < 0 or os.environ.get("GRAFTBENCH_QUIET") == "1"
        return False if quiet or hasattr(self.config, "workerinput") else TerminalSink(self.config)

    @property
    def screening(self):
        """The run's screens and graft selections (bench.run.screen_run); None without --screen."""
        if self._screening is None and self.screen_options is not None:
            from bench.run.screen_run import ScreenRun

            self._screening = ScreenRun(self.screen_options, self.profile, self.store,
                                        self.workspace, feature_dtype=self.feature_dtype,
                                        rerun=self.rerun, run_cell=self.run)
        return self._screening

    @property
    def robustness(self):
        """The run's robustness cases (bench.run.robust_run); --robustness only."""
        if self._robustness is None:
            from bench.run.robust_run import RobustRun

            self._robustness = RobustRun(self.profile, self.workspace, rerun=self.rerun)
        return self._robustness

    # --- one cell: plan, then run ------------------------------------------------------------
    def run(self, cell: CellSpec):
        """Plan the cell (resume the stored record, or measure, and with what: bench.run.plan),
        carry the plan out, then the baseline's cell checks (a regression fails this case in
        one line). Under --screen, a cell of an encoder the screen dropped is skipped, saying
        why, before anything trains."""
        if self.screening is not None and (why := self.screening.dropped_reason(cell)):
            from bench.run.screen_run import DROPPED

            pytest.skip(DROPPED + why)
        if cell.id in self.records:  # a short graft the selection ran before its own case
            return self.records[cell.id]
        with self._claim(cell):  # another run on this results dir waits here, then resumes
            if (line := self.store.set_aside(cell.id)) is not None:
                self.set_aside_lines.append(line)
                say(self.progress_sink(), line)
            cell_plan = self.plan(cell)
            if cell_plan.resume is not None:
                record = cell_plan.resume
                self.outcomes[cell.id] = "resumed"
            else:
                record = self._measure(cell_plan)
                self.outcomes[cell.id] = "measured"
        self.baseline.check_cell(cell, record)
        self.records[cell.id] = record
        return record

    def _claim(self, cell: CellSpec):
        """The results store's claim on `cell` while it is planned and measured here (a job
        array measures in its own tasks: the array is the one claimant, nothing to claim)."""
        import contextlib

        if self.options.executor != "local":
            return contextlib.nullcontext()
        return self.store.cell_lock(cell.id, on_wait=lambda: say(
            self.progress_sink(), f"{cell.id}: another process is measuring it (its claim "
                                  f"{self.store.claim_path(cell.id)}); waiting for its record"))

    @property
    def projectors(self) -> dict:
        """Projectors measured cells handed back, by `CellContext.keep_as`: later cells' plans
        take them (a graft's shuffled / zero-at-eval controls)."""
        if "_projectors" not in self.__dict__:
            self._projectors = {}
        return self._projectors

    def plan(self, cell: CellSpec):
        """Resume or measure `cell` (bench.run.plan.plan: reads the store, writes nothing)."""
        from bench.results.current import RunConditions
        from bench.run.plan import plan

        run = RunConditions(protocol_hash=self.profile.protocol.hash,
                            feature_dtype=self.feature_dtype, rollouts=self.rollouts)
        return plan(cell, self.store, run, weights=lambda wanted: self._weights(cell, wanted),
                    rerun=self.rerun, features_mode=self.features_mode,
                    projectors=self.projectors,
                    feature_transform=self.baseline.feature_transform(cell, self.workspace))

    def _weights(self, cell: CellSpec, run):
        """`run` with the weights and normaliser this cell is measured on (loads the policy)."""
        from bench.results.record import checkpoint_revision

        ws = self.workspace()
        return replace(run, revision=checkpoint_revision(ws.checkpoint(cell.backbone, cell.suite)),
                       normalizer_fingerprint=ws.normalizer(cell.backbone, cell.suite).fingerprint)

    def _measure(self, cell_plan):
        """Measure a planned cell here (or through the job array); keep what it trained."""
        cell = cell_plan.cell
        if cell_plan.discard:  # a degraded record never outlives its run
            self.store.forget(cell.id)
        self._say_start(cell_plan)
        if self.options.executor != "local":
            return self._run_submitted(cell)
        try:
            result = self.cell_runner(cell, self.workspace(), cell_plan.context)
        except Exception as e:
            from bench.results.record import Failure

            self.store.write_failure(Failure.of(cell, self.profile.protocol.hash, e))
            if isinstance(e, _unavailable_errors()):  # a missing artifact: its line, no traceback
                pytest.fail(f"{cell.id}: {type(e).__name__}: {e}", pytrace=False)
            raise
        if result.trained is not None:
            self.projectors[cell_plan.context.keep_as] = result.trained
        record = result.record
        say(self.workspace().progress, f"{cell.id}: MSE {record.mse_in():.4f} "
                                       f"normalised ({record.run.total_s:.1f} s)")
        return record

    def pytest_runtest_logreport(self, report) -> None:
        """Each grid case's outcome, serial or from xdist workers (user_properties travel)."""
        from bench.summary import OUTCOME_PROPERTY, cell_id_of, failure_line

        cell = cell_id_of(report.nodeid)
        if "::test_robust[" in report.nodeid:  # a robustness case, not its cell's outcome
            return
        if cell in self.screens_selected and report.when == "call":
            self.screening.note_report(cell, report)  # an xdist worker's screen
        if cell is None or cell not in self.selected or report.when != "call":
            return
        if report.skipped and self.screening is not None:
            self.screening.note_report(cell, report)  # dropped by the screen (here or a worker)
        if report.passed:
            outcome = dict(report.user_properties).get(OUTCOME_PROPERTY)
            self.outcomes[cell] = outcome or self.outcomes.get(cell, "measured")
        elif report.failed:
            self.outcomes[cell] = failure_line(self.results_dir, cell, report.longreprtext)

    def _say_start(self, cell_plan) -> None:
        cell, ws = cell_plan.cell, self.workspace()
        position = self.selected.index(cell.id) + 1 if cell.id in self.selected else "?"
        say(ws.progress, f"cell {position}/{len(self.selected)} {cell.id}: "
                         f"{cell_plan.work(self.profile.protocol.steps)} "
                         "offline MSE on the held-out windows")

    def _run_submitted(self, cell: CellSpec) -> dict:
        """--executor slurm|submitit-local: the first case submits every selected cell that has
        no current record as ONE job array; each case then waits for its own task."""
        from bench.run.executors import CellArray, CellJob
        from external.paths import cache_dir
        from bench.results.record import Failure

        if self._cell_array is None:
            self._cell_array = CellArray(self.options.executor, self.results_dir / "submitit",
                                         self.options.slurm)
            items = self.config.pluginmanager.get_plugin("session").items  # after -k / -m
            params = [getattr(getattr(i, "callspec", None), "params", {}) for i in items]
            cells = [p.get("graft_cell", p.get("control_cell", p.get("tier_cell")))
                     for p in params]
            todo = [c for c in cells if isinstance(c, CellSpec) and self.plan(c).resume is None
                    and not (self.screening and self.screening.dropped_reason(c))]
            paths = (str(self.results_dir), str(cache_dir()))
            self._cell_array.submit([CellJob(c, self.profile, *paths, self.features_mode,
                                             self.rollouts, self.feature_dtype,
                                             *self.rollout_batch) for c in todo])
        try:
            return self._cell_array.result(cell.id)
        except Exception as e:  # the task died before writing its own failure record
            self.store.write_failure(Failure.of(cell, self.profile.protocol.hash, e))
            raise

    # --- the session's ends -----------------------------------------------------------------
    def preflight(self, cells: list[CellSpec]) -> None:
        """Hub grids: list every artifact the selected cells read; stop (UsageError, no cell
        run) when one is missing. --collect-only shows the list and stops anyway."""
        if self.profile.source != "hub" or not cells:
            return
        from bench.preflight import cells_artifacts, missing_summary, render

        artifacts = cells_artifacts(cells)
        reporter = self.config.pluginmanager.get_plugin("terminalreporter")
        screen = render(artifacts)
        if reporter is not None:
            reporter.write_line(screen)
        else:
            sys.stderr.write(screen + "\n")
        if any(not a.present for a in artifacts) and not self.config.option.collectonly:
            raise pytest.UsageError(missing_summary(artifacts))

    @property
    def ran_cells(self) -> list[str]:
        """The selected cells the screen did not drop: what grid.json and the baseline expect."""
        dropped = self.screening.dropped if self.screening is not None else {}
        return [c for c in self.selected if c not in dropped]

    def finish_baseline(self) -> list[tuple[str, str]]:
        """The baseline's save / compare over the stored records; the report sections it adds."""
        records = {cid: r for cid in self.ran_cells if (r := self.store.load(cid)) is not None}
        return self.baseline.finish(self.ran_cells, records)

    def finish(self, sections: list[tuple[str, str]] = ()) -> Path | None:
        """REPORT.md (with the baseline's sections) when a cell finished in this run; None when
        nothing new finished (an existing report is left as it is)."""
        outcomes = list(self.outcomes.values())
        if self._robustness is not None:
            outcomes += list(self._robustness.outcomes.values())
        if self.screening is not None:
            outcomes += list(self.screening.outcomes.values())
            if self.selected and self.screening.dropped:  # grid.json: what was meant to run
                self.store.write_grid(self.ran_cells, self.profile.name)
        measured = any(o == "measured" for o in outcomes)
        resumed = any(o == "resumed" for o in outcomes)
        if not (self.selected or self.screens_selected or self.robust_selected) or not (
                measured or (resumed and not self.report_path.exists())):
            return None
        self.report_written = self.report_builder(self.results_dir, self.report_path,
                                                  extra_sections=sections)
        return self.report_written


def _default_workspace(session: GraftSession):
    """The real workspace, with this process's torch threads set first."""
    from bench.run.workspace import Workspace

    sink = session.progress_sink()
    if not hasattr(session.config, "workerinput"):  # workers: bench.plugin split the CPUs
        import torch

        threads, why = serial_threads()
        torch.set_num_threads(threads)
        say(sink, f"torch threads: {threads} ({why})")
    batch, envs = session.rollout_batch
    return Workspace(session.profile, session.store, progress=sink, rollouts=session.rollouts,
                     feature_dtype=session.feature_dtype, rollout_batch=batch, rollout_envs=envs)


def serial_threads() -> tuple[int, str]:
    """Torch threads for a serial run, and why: OMP_NUM_THREADS when set, else the CPUs the
    1-minute load leaves free (at least 1). torch's default (every CPU) against one other busy
    process made the tiny grid's steps 20x slower (docs/SCALING.md: 4.3 s -> 88-99 s)."""
    cpus = len(os.sched_getaffinity(0))
    if os.environ.get("OMP_NUM_THREADS"):
        return max(1, int(os.environ["OMP_NUM_THREADS"])), "OMP_NUM_THREADS"
    load = os.getloadavg()[0]
    # Whole busy CPUs only: the load a finished job leaves behind decays over minutes.
    free = max(1, min(cpus, cpus - int(load)))
    return free, f"{cpus} CPUs, 1-min load {load:.1f}; set OMP_NUM_THREADS to choose"
