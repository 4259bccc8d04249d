"""One pytest run of the grid: `GraftSession` holds the profile, the results store, the
workspace, the cell service (bench.cell.service: every cell goes through it), the baseline work
(save / compare / fail, bench.regression.run) and what collection selected.

bench.plugin's hooks only hand work on to it, through its methods: `collected` freezes the
selection once collection ends. Its seams are one frozen `Seams` value, replaced before the first
cell runs through `use_seams` (tests do): `cell_runner(cell, workspace, context) -> CellResult`
(None: the service's own, bench.cell.runner.measure, with the context the cell's plan gave),
`workspace_factory(session) -> workspace`, `report_builder(results_dir, path, extra_sections=)`
(bench.report.build_report).
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import pytest

from bench.grid.cells import CellSpec
from bench.options import parse_options
from bench.startup import check_startup, check_writable, collects_grid, offline_env
from bench.progress import QUIET, TerminalSink, WorkerSink, say
from bench.cell.outcome import MEASURED, OUTCOME_PROPERTY, Outcome, Status, failed
from bench.regression.run import BaselineRun


def _unavailable_errors() -> tuple[type, ...]:
    """Errors that mean "an artifact is missing" and carry their own one-line fix."""
    from backbones.base import BackboneUnavailable
    from bench.suites.base import SuiteUnavailable
    from encoders.registry import EncoderUnavailable

    return (BackboneUnavailable, SuiteUnavailable, EncoderUnavailable)


def _build_report(results_dir, path, extra_sections=()):
    from bench.report.build import build_report

    return build_report(results_dir, path, extra_sections=list(extra_sections))


@dataclass(frozen=True)
class Seams:
    """What tests replace (module docstring); the defaults are the real ones."""

    cell_runner: Callable | None = None  # None: the service's own (bench.cell.runner.measure)
    workspace_factory: Callable = field(default=lambda session: _default_workspace(session))
    report_builder: Callable = _build_report


@dataclass(frozen=True)
class Selection:
    """What collection selected (after -k / -m), as ids: grid cells (grafts, controls, short
    grafts), screen cases, robustness cases. Frozen: set once per collection."""

    cells: tuple[str, ...] = ()
    screens: tuple[str, ...] = ()
    robust: tuple[str, ...] = ()
    sliced: bool = False  # -k / -m deselected a grid case (grid.json: `_write_grid`)

    def __bool__(self) -> bool:
        return bool(self.cells or self.screens or self.robust)


class GraftSession:
    """State of one pytest run of the grid: profile, store, workspace, baseline, what ran."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        # Start-up: every option, parsed once into a frozen value before collection
        # (bench.options): a bad one is ONE UsageError screen, exit 4, no cell run.
        self.options = options = parse_options(config)
        self.startup_lines = list(options.startup_lines)  # printed at the session's start
        offline_env(self.profile.offline)
        self.seams = Seams()  # module docstring; replaced only through use_seams
        self.baseline = BaselineRun(options.baseline, self.profile.protocol.hash, self.profile)
        self._workspace = None
        self._store = None
        self._cells = None  # the cell service (bench.cell.service), built on first use
        self.selection = Selection()  # what collection selected: frozen, set by `collected`
        self._robustness = None
        self._screening = None
        self._pack_units = None  # (units,): pack_units, drawn once the selection is known
        self.report_written: Path | None = None
        self.report_error: str | None = None  # why REPORT.md could not be written, if it failed
        # Names, user paths, output folders: checked here when this run collects the grid (an
        # xdist worker's controller checked them); else at collection (bench.plugin).
        self._names_checked = collects_grid(config) and not hasattr(config, "workerinput")
        if self._names_checked:
            from bench.memory import measuring_processes

            rollout_workers = options.rollout_batching.workers if options.rollouts else 0
            self.startup_lines += check_startup(self.profile, options.labels, options.screen is
                                                not None, measuring_processes(config, options),
                                                rollout_workers)
            self.store  # opens (creates, probes) the results dir
            self.check_report()

    def use_seams(self, **changes) -> None:
        """Replace seams (Seams' fields) before the first cell (after it: part of the run only)."""
        if self._cells is not None or self._workspace is not None:
            raise RuntimeError("use_seams after the first cell: set seams at pytest_configure")
        self.seams = replace(self.seams, **changes)

    def collected(self, selection: Selection, cells: list[CellSpec] = ()) -> None:
        """Collection's selection (bench.plugin, after -k / -m; an xdist controller: what its
        workers collected), `cells` its grid cells. Where the run's ends run (not an xdist
        worker): the results dir and --report checked, the paper preflight, grid.json written."""
        self.selection = selection
        self.pack_units()  # now: before any process of the run measures a cell
        if hasattr(self.config, "workerinput") or not (selection.cells or selection.screens):
            return
        self.store  # opened at start-up (bench/ runs), else here: a one-line UsageError if it cannot
        self.check_report(len(self.store.stored_ids() | set(selection.cells)))
        if self.profile.source == "hub" and cells:  # every artifact listed; one missing: stop
            from bench.preflight import stop_on_missing

            stop_on_missing(list(cells), self.config, self.store)
        if selection.cells:  # now, so a stopped run leaves the list (--screen: again at the end)
            self._write_grid(self.selection.cells)

    def check_report(self, cells_after: int | None = None) -> None:
        """--report by bench.outputs' rule, a UsageError before any cell (`cells_after`: the
        most cells the report holds, once the selection is known)."""
        from bench.outputs import report_refusal

        check_writable("--report", self.report_path.parent)
        problem = report_refusal("--report", self.report_path, cells_after=cells_after,
                                 replace=self.options.replace_report)
        if problem:
            self.store.remove_if_unused()  # stopped before any cell: no empty folders left
            raise pytest.UsageError(problem)

    def _write_grid(self, cells: list[str]) -> None:
        """grid.json (store.write_grid), never under --collect-only: it lists ids, expects none.
        The selected cells not in `cells` (the screen's drops) leave an earlier slice's list."""
        if not self.config.option.collectonly:
            dropped = set(self.selection.cells) - set(cells)
            self.store.write_grid(list(cells), self.profile.name, add=self.selection.sliced,
                                  drop=dropped)

    def check_names_once(self) -> list[str]:
        """The start-up check of names and paths, when no earlier hook ran it (a grid module
        outside bench/, collected by tests): its lines, or [] when already checked."""
        if self._names_checked:
            return []
        self._names_checked = True
        return check_startup(self.profile)

    # What the options say, by the names the cells' code reads (one value: self.options).
    profile = property(lambda self: self.options.profile)
    results_dir = property(lambda self: self.options.results_dir)
    report_path = property(lambda self: self.options.report_path)
    rerun = property(lambda self: self.options.rerun)
    rollouts = property(lambda self: self.options.rollouts)
    rollout_batching = property(lambda self: self.options.rollout_batching)
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
            self._workspace = self.seams.workspace_factory(self)
        return self._workspace

    def progress_sink(self):
        """The terminal; an xdist worker's lines go there too, whole lines named by the worker
        (`-n 2` used to be silent for as long as a release trained); the null sink under -q
        and GRAFTBENCH_QUIET=1."""
        if self.config.get_verbosity() < 0 or os.environ.get("GRAFTBENCH_QUIET") == "1":
            return QUIET
        worker = getattr(self.config, "workerinput", {}).get("workerid")
        return WorkerSink(self.config, worker) if worker else TerminalSink(self.config)

    @property
    def screening(self):
        """The run's screens and graft selections (bench.cell.screening); None without --screen."""
        if self._screening is None and self.screen_options is not None:
            from bench.cell.screening import ScreenRun

            self._screening = ScreenRun(self.screen_options, self.cells)
        return self._screening

    @property
    def robustness(self):
        """The run's robustness cases (bench.robust.cases); --robustness only."""
        if self._robustness is None:
            from bench.robust.cases import RobustRun

            self._robustness = RobustRun(self.profile, self.workspace, rerun=self.rerun)
        return self._robustness

    # --- one cell: through the cell service --------------------------------------------------
    @property
    def cells(self):
        """The run's one cell service (bench.cell.service): every cell case, the screen's short
        grafts and, with --executor, the job array's tasks measure through it."""
        if self._cells is None:
            from bench.cell.service import CellService, RunSettings, measure_here

            o = self.options
            settings = RunSettings(rerun=o.rerun, features_mode=o.features_mode,
                                   feature_dtype=o.feature_dtype, rollouts=o.rollouts,
                                   pack_grafts=o.pack_grafts)
            self._cells = CellService(
                self.profile, self.store, self.workspace, settings,
                runner=self.seams.cell_runner or measure_here,
                job_array=self._job_array(settings) if o.executor != "local" else None,
                array_candidates=self._array_candidates,
                feature_transform=lambda cell: self.baseline.feature_transform(
                    cell, self.workspace),
                order=lambda: self.selection.cells, claim=o.executor == "local",
                pack_candidates=self._pack_candidates)
        return self._cells

    def _job_array(self, settings):
        """--executor slurm|submitit-local: the job array the cell service hands the plans of the
        cells to measure (bench.cell.executors; each task runs a cell service of its own)."""
        from bench.cell.executors import CellArray, JobArray

        array = CellArray(self.options.executor, self.results_dir / "submitit", self.options.slurm)
        return JobArray(array, self.profile, self.results_dir, settings, self.rollout_batching)

    def _selected_specs(self) -> list[CellSpec]:
        """The selected cells (after -k / -m), in run order."""
        from bench.grid.cells import grid_cells

        specs = {c.id: c for c in grid_cells(self.profile, self.screen_options is not None)}
        return [specs[i] for i in self.selection.cells if i in specs]

    def _array_candidates(self) -> list[CellSpec]:
        """The selected cells an --executor job array may measure, in run order: none the screen
        dropped (the cell service submits those without a current record)."""
        return [c for c in self._selected_specs()
                if not (self.screening and self.screening.dropped_reason(c))]

    def _pack_candidates(self, cell: CellSpec) -> list[CellSpec]:
        """The selected cells that may share `cell`'s pack (bench.cell.pack_run.candidates),
        none the screen dropped (short grafts run before the screen's selection exists)."""
        from bench.cell.pack_run import candidates

        alike = candidates(cell, self._selected_specs(), self.pack_units())
        if self.screening is None or cell.spec.tier:
            return alike
        return [c for c in alike if not self.screening.dropped_reason(c)]

    def pack_units(self) -> dict[str, str] | None:
        """bench.cell.pack_run.run_units, drawn once when collection ends: no process of the run
        has measured a cell yet, so the controller and each worker draw the same units."""
        if self._pack_units is None:
            from bench.cell.pack_run import run_units
            from bench.scheduling import units_per_cell

            self._pack_units = (run_units(self.options, self.profile.protocol.hash,
                                          units_per_cell(self.profile), self._selected_specs(),
                                          self.store),)
        return self._pack_units[0]

    outcomes = property(lambda self: self.cells.outcomes)  # cell id -> Outcome
    records = property(lambda self: self.cells.records)
    set_aside_lines = property(lambda self: self.cells.set_aside_lines)

    def run(self, cell: CellSpec):
        """The cell through the cell service, then the baseline's cell checks (a regression
        fails this case in one line). Under --screen, a cell of an encoder the screen dropped
        is skipped, saying why, before anything trains; a missing artifact fails in its line."""
        if self.screening is not None and (why := self.screening.dropped_reason(cell)):
            from bench.cell.screening import DROPPED

            pytest.skip(DROPPED + why)
        try:
            record = self.cells.run(cell)
        except _unavailable_errors() as e:  # its one line, no traceback
            pytest.fail(f"{cell.id}: {type(e).__name__}: {e}", pytrace=False)
        self.baseline.check_cell(cell, record)
        return record

    def pytest_runtest_logreport(self, report) -> None:
        """Each grid case's outcome, serial or from xdist workers (user_properties travel)."""
        from bench.summary import cell_id_of, failure_line

        cell = cell_id_of(report.nodeid)
        if "::test_robust[" in report.nodeid:  # a robustness case, not its cell's outcome
            return
        if cell in self.selection.screens and report.when == "call":
            self.screening.note_report(cell, report)  # an xdist worker's screen
        if cell is None or cell not in self.selection.cells or report.when != "call":
            return
        if report.skipped and self.screening is not None:
            self.screening.note_report(cell, report)  # dropped by the screen (here or a worker)
        if report.passed:
            told = dict(report.user_properties).get(OUTCOME_PROPERTY)
            self.outcomes[cell] = (Outcome.of_text(told) if told
                                   else self.outcomes.get(cell, MEASURED))
        elif report.failed:
            self.outcomes[cell] = failed(failure_line(self.results_dir, cell,
                                                      report.longreprtext))

    # --- the session's ends -----------------------------------------------------------------
    @property
    def ran_cells(self) -> list[str]:
        """The selected cells the screen did not drop: what grid.json and the baseline expect."""
        dropped = self.screening.dropped if self.screening is not None else {}
        return [c for c in self.selection.cells if c not in dropped]

    def finish(self, exitstatus: int) -> int:
        """The session's end, where it runs (not an xdist worker: the controller compares and
        reports from the shared store): the baseline's save / compare, grid.json under --screen,
        REPORT.md; returns the run's exit status: a failed comparison or report is an internal
        error and a rank flip a failure, never a success."""
        if hasattr(self.config, "workerinput") or not self.selection:
            return exitstatus
        try:
            records = {c: r for c in self.ran_cells if (r := self.store.load(c)) is not None}
            sections = self.baseline.finish(self.ran_cells, records)
        except Exception as e:  # a comparison that could not be made must not pass silently
            sys.stderr.write(f"\n[graftbench] baseline compare/save failed: "
                             f"{type(e).__name__}: {e}\n")
            exitstatus, sections = pytest.ExitCode.INTERNAL_ERROR, []
        if self.baseline.rank_flipped and exitstatus == 0:
            exitstatus = pytest.ExitCode.TESTS_FAILED
        if self.screening is not None and self.selection.cells:
            self._write_grid(self.ran_cells)
        self._report(sections)
        if self.report_error is not None and exitstatus == 0:
            exitstatus = pytest.ExitCode.INTERNAL_ERROR
        return exitstatus

    def _report(self, sections: list[tuple[str, str]]) -> None:
        """REPORT.md (with the baseline's sections) when a cell finished in this run; nothing
        when nothing new finished (an existing report is left as it is) or when writing it
        failed (`report_error` says why)."""
        outcomes = list(self.outcomes.values())
        if self._robustness is not None:
            outcomes += list(self._robustness.outcomes.values())
        if self.screening is not None:
            outcomes += list(self.screening.outcomes.values())
        statuses = {o.status for o in outcomes}
        if not (Status.MEASURED in statuses or (
                Status.RESUMED in statuses and not self.report_path.exists())):
            return
        try:
            self.report_written = self.seams.report_builder(self.results_dir, self.report_path,
                                                            extra_sections=sections)
        except Exception as e:  # a report bug must not hide the cell results: said, kept
            self.report_error = f"{type(e).__name__}: {e}"
            sys.stderr.write(f"\n[graftbench] REPORT.md not written: {self.report_error}\n")

    def display(self, reporter) -> None:
        """The run's summary at the end of pytest's (bench.summary's lines, the baseline's)."""
        selection = self.selection
        if not (selection.cells or selection.screens) or hasattr(self.config, "workerinput"):
            return
        from bench.summary import screen_summary_lines, summary_lines

        reporter.write_sep("-", "graftbench")
        lines = summary_lines(self.profile.name, self.profile.protocol.hash, self.outcomes,
                              len(selection.cells), self.results_dir, self.report_path,
                              self.report_written is not None, self.report_error)
        if self.screening is not None:
            lines[2:2] = screen_summary_lines(self.screening.outcomes, self.screening.dropped)
        lines += [f"set aside: {line}" for line in self.set_aside_lines]
        for line in lines:
            reporter.write_line(line)
        self.baseline.summary(reporter)


def _default_workspace(session: GraftSession):
    """The real workspace, with this process's torch threads set first."""
    sink = session.progress_sink()
    # The first import of LeRobot: 33 s on 2 busy cores, said before so that it is not silent.
    say(sink, "importing torch and LeRobot (once per process)")
    from bench.resources.workspace import Workspace

    if not hasattr(session.config, "workerinput"):  # workers: bench.plugin split the CPUs
        import torch

        from bench.scheduling import serial_threads

        threads, why = serial_threads()
        torch.set_num_threads(threads)
        say(sink, f"torch threads: {threads} ({why})")
    return Workspace(session.profile, session.store, progress=sink, rollouts=session.rollouts,
                     feature_dtype=session.feature_dtype,
                     rollout_batching=session.rollout_batching)
