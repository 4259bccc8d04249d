"""The pytest plugin: the grid parametrisation, the session object, the report hook (options:
bench.options).

Hooks only hand work on: `pytest_configure` builds ONE `GraftSession`; cells run through it;
`pytest_sessionfinish` asks it for the report (controller only under xdist).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from bench.cells import GRAFT, CellSpec, control_cells, graft_cells
from bench.options import (  # noqa: F401  (pytest_addoption: the hook, found here by name)
    check_rollouts_possible,
    check_writable,
    offline_env,
    validate_names,
    build_profile,
    pytest_addoption,
    report_path,
)
from bench.paths import REPO_ROOT
from bench.progress import say

SESSION_KEY = pytest.StashKey["GraftSession"]()


def _unavailable_errors() -> tuple[type, ...]:
    """Errors that mean "an artifact is missing" and carry their own one-line fix."""
    from backbones.base import BackboneUnavailable
    from bench.suites.base import SuiteUnavailable
    from encoders.registry import EncoderUnavailable

    return (BackboneUnavailable, SuiteUnavailable, EncoderUnavailable)


class GraftSession:
    """State of one pytest run of the grid: profile, store, workspace, what ran."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.profile = build_profile(config)
        offline_env(self.profile.offline)
        results = config.getoption("--results-dir")
        self.results_dir = Path(results) if results else REPO_ROOT / ".graftbench" / "results" / self.profile.name
        self.report_path = report_path(config.getoption("--report"), results, self.profile.name,
                                       self.results_dir)
        self.rerun = bool(config.getoption("--rerun"))
        self.features_mode = config.getoption("--features")
        self.rollouts = int(config.getoption("--rollouts") or 0)
        if self.rollouts < 0:
            raise pytest.UsageError(f"--rollouts {self.rollouts}: give episodes per task >= 0")
        if self.rollouts:
            check_rollouts_possible(self.profile)
        self._workspace = None
        self._store = None
        self.outcomes: dict[str, str] = {}  # cell id -> "measured" | "resumed" | failure line
        self.selected: list[str] = []
        self.extra_sections: list[tuple[str, str]] = []
        self._cell_array = None  # bench.executors.CellArray, when --executor is not local

    @property
    def store(self):
        from bench.store import ResultsDirError, ResultStore

        if self._store is None:
            try:  # first opened at collection: a UsageError there, never an INTERNALERROR
                self._store = ResultStore(self.results_dir)
            except ResultsDirError as e:
                raise pytest.UsageError(f"--results-dir: {e}") from None
        return self._store

    def workspace(self):
        from bench.workspace import Workspace

        if self._workspace is None:
            sink = self.progress_sink()
            if not hasattr(self.config, "workerinput"):  # workers: _configure_scale split CPUs
                import torch

                threads, why = serial_threads()
                torch.set_num_threads(threads)
                say(sink, f"torch threads: {threads} ({why})")
            self._workspace = Workspace(self.profile, self.store, progress=sink,
                                        rollouts=self.rollouts)
        return self._workspace

    def progress_sink(self):
        """The terminal, or False: under -q, GRAFTBENCH_QUIET=1 and in xdist workers (their
        output would interleave with the controller's)."""
        from bench.progress import TerminalSink

        quiet = self.config.get_verbosity() < 0 or os.environ.get("GRAFTBENCH_QUIET") == "1"
        return False if quiet or hasattr(self.config, "workerinput") else TerminalSink(self.config)

    def run(self, cell: CellSpec) -> dict:
        """The stored record when current (resume), else measure the cell now."""
        from bench.runner import run_cell

        if not self.rerun:
            record = self._current(cell)
            if record is not None:
                self.outcomes[cell.id] = "resumed"
                return record
        self._say_start(cell)
        if self.config.getoption("--executor") != "local":
            record = self._run_submitted(cell)
            self.outcomes[cell.id] = "measured"
            return record
        try:
            record = run_cell(cell, self.workspace(), features_mode=self.features_mode)
        except Exception as e:
            self.store.write_failure({
                "cell_id": cell.id, "kind": cell.kind, "backbone": cell.backbone,
                "suite": cell.suite, "encoder": cell.encoder, "seed": cell.seed,
                "variant": cell.variant, "error": f"{type(e).__name__}: {e}",
                "protocol_hash": self.profile.protocol.hash,
            })
            if isinstance(e, _unavailable_errors()):  # a missing artifact: its line, no traceback
                pytest.fail(f"{cell.id}: {type(e).__name__}: {e}", pytrace=False)
            raise
        self.outcomes[cell.id] = "measured"
        say(self.workspace().progress, f"{cell.id}: MSE {record['mse']['normalized']:.4f} "
                                       f"normalised ({record['timings_s']['total']:.1f} s)")
        return record

    def pytest_runtest_logreport(self, report) -> None:
        """Each grid case's outcome, serial or from xdist workers (user_properties travel)."""
        from bench.summary import OUTCOME_PROPERTY, cell_id_of, failure_line

        cell = cell_id_of(report.nodeid)
        if cell is None or cell not in self.selected or report.when != "call":
            return
        if report.passed:
            outcome = dict(report.user_properties).get(OUTCOME_PROPERTY)
            self.outcomes[cell] = outcome or self.outcomes.get(cell, "measured")
        elif report.failed:
            self.outcomes[cell] = failure_line(self.results_dir, cell, report.longreprtext)

    def _say_start(self, cell: CellSpec) -> None:
        from bench.runner import shared_projector_key

        ws = self.workspace()
        position = self.selected.index(cell.id) + 1 if cell.id in self.selected else "?"
        if not cell.trains_projector:
            work = "no training,"
        elif cell.kind != GRAFT and shared_projector_key(cell, self.features_mode) in ws.trained_projectors:
            work = "its graft's trained projector, then"
        else:
            work = f"{self.profile.protocol.steps} projector steps, then"
        say(ws.progress, f"cell {position}/{len(self.selected)} {cell.id}: {work} "
                         "offline MSE on the held-out windows")

    def _current(self, cell: CellSpec) -> dict | None:
        """The stored record of `cell` if it is current: same protocol hash and, with
        --rollouts, closed-loop episodes of the requested size."""
        from bench.closed_loop import has_rollouts

        record = self.store.current(cell.id, self.profile.protocol.hash)
        if record is not None and self.rollouts and not has_rollouts(record, self.rollouts):
            return None  # the offline part is current, the closed loop is not: measure again
        if record is not None:
            # Measured with another normaliser (other stats or checkpoint): measure again.
            expected = self.workspace().normalizer(cell.backbone, cell.suite).fingerprint
            if (record.get("checkpoint") or {}).get("normalizer_fingerprint") != expected:
                return None
        return record

    def _run_submitted(self, cell: CellSpec) -> dict:
        """--executor slurm|submitit-local: the first case submits every selected cell that has
        no current record as ONE job array; each case then waits for its own task."""
        from bench.executors import CellArray, CellJob, SlurmOptions, failure_record
        from bench.paths import cache_dir

        if self._cell_array is None:
            opt = self.config.getoption
            slurm = SlurmOptions(
                partition=opt("--slurm-partition"), time_min=opt("--slurm-time"),
                gpus_per_task=opt("--slurm-gpus-per-task"),
                array_parallelism=opt("--slurm-array-parallelism"),
            )
            self._cell_array = CellArray(opt("--executor"), self.results_dir / "submitit", slurm)
            items = self.config.pluginmanager.get_plugin("session").items  # after -k / -m
            params = [getattr(getattr(i, "callspec", None), "params", {}) for i in items]
            cells = [p.get("graft_cell", p.get("control_cell")) for p in params]
            todo = [c for c in cells if isinstance(c, CellSpec) and (
                self.rerun or not self._current(c))]
            paths = (str(self.results_dir), str(cache_dir()))
            self._cell_array.submit([CellJob(c, self.profile, *paths, self.features_mode,
                                             self.rollouts) for c in todo])
        try:
            return self._cell_array.result(cell.id)
        except Exception as e:  # the task died before writing its own failure record
            self.store.write_failure(failure_record(cell, self.profile, e))
            raise

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

    def finish(self) -> Path | None:
        measured = any(o == "measured" for o in self.outcomes.values())
        resumed = any(o == "resumed" for o in self.outcomes.values())
        if not self.selected or not (measured or (resumed and not self.report_path.exists())):
            return None  # nothing new finished: an existing report is left as it is
        from bench.report import build_report

        return build_report(self.results_dir, self.report_path, extra_sections=self.extra_sections)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "cell: a graftbench grid cell")
    _configure_scale(config)
    session = GraftSession(config)
    config.stash[SESSION_KEY] = session
    config.pluginmanager.register(session, "graftbench-session")  # its hook methods below


def _configure_scale(config: pytest.Config) -> None:
    """`-n N` implies `--dist loadgroup` (one backbone per worker: a 3.3B model loads once per
    worker); an xdist worker takes GPU (worker index mod GPU count) when GPUs exist."""
    numprocesses = getattr(config.option, "numprocesses", None)
    if numprocesses and config.getoption("--executor") != "local":
        executor = config.getoption("--executor")
        raise pytest.UsageError(f"-n {numprocesses} with --executor {executor}: "
                                "pick one (drop -n or the executor)")
    if numprocesses and getattr(config.option, "dist", "no") in ("no", "load"):
        config.option.dist = "loadgroup"
    workerinput = getattr(config, "workerinput", {})
    worker = workerinput.get("workerid")  # "gw0", "gw1", ...
    if worker:
        import torch

        if torch.cuda.is_available():
            torch.cuda.set_device(int(worker[2:]) % torch.cuda.device_count())
        torch.set_num_threads(worker_threads(workerinput.get("workercount", 1)))


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


def worker_threads(workers: int) -> int:
    """Torch threads for one of `workers` xdist workers: the CPUs split between them, unless
    OMP_NUM_THREADS says otherwise. Each worker keeping torch's default (all CPUs) made `-n 2` on
    2 cores 4.6x SLOWER than one process (18 tiny cells: 180 s alone, 828 s with -n 2)."""
    if os.environ.get("OMP_NUM_THREADS"):
        return max(1, int(os.environ["OMP_NUM_THREADS"]))
    return max(1, len(os.sched_getaffinity(0)) // max(1, workers))


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """loadgroup by backbone, read from the cell id: each worker holds ONE backbone. With more
    workers than backbones, a backbone's cells are dealt round-robin into N // B groups so all
    N workers work. (xdist's own loadgroup reads a nodeid suffix that pytest 9.2 no longer lets
    it add, pytest-dev/pytest-xdist#1386: it silently spread every backbone over all workers.)"""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    gs: GraftSession = config.stash[SESSION_KEY]
    backbone_of = {c.id: c.backbone for c in graft_cells(gs.profile) + control_cells(gs.profile)}

    class BackboneScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            cell_id = nodeid.split("@")[0].rsplit("[", 1)[-1].rstrip("]")
            if cell_id not in backbone_of:
                return nodeid
            # gs.selected: the cells the workers collected (pytest_xdist_node_collection_finished)
            mine = [c for c in gs.selected if backbone_of.get(c) == backbone_of[cell_id]]
            backbones = {backbone_of[c] for c in gs.selected if c in backbone_of}
            groups = max(1, self.numnodes // max(1, len(backbones)))
            position = mine.index(cell_id) if cell_id in mine else 0
            return f"{backbone_of[cell_id]}:{position % groups}"

    return BackboneScheduling(config, log)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids: list[str]) -> None:
    """xdist controller: it collects nothing itself, so the cells its workers collected (after
    -k/-m) are the selection that grid.json and the report expect."""
    gs: GraftSession = node.config.stash[SESSION_KEY]
    if gs.selected:
        return  # every worker collects the same items
    known = {c.id for c in graft_cells(gs.profile) + control_cells(gs.profile)}
    params = [i.split("@")[0].rsplit("[", 1)[-1].rstrip("]") for i in ids]
    gs.selected = [p for p in params if p in known]
    if gs.selected:
        gs.store.write_grid(gs.selected, gs.profile.name)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    names = metafunc.fixturenames
    if "graft_cell" not in names and "control_cell" not in names:
        return
    session: GraftSession = metafunc.config.stash[SESSION_KEY]
    validate_names(session.profile)
    cells = graft_cells(session.profile) if "graft_cell" in names else control_cells(session.profile)
    argname = "graft_cell" if "graft_cell" in names else "control_cell"
    metafunc.parametrize(
        argname,
        [pytest.param(c, id=c.id, marks=pytest.mark.xdist_group(c.backbone)) for c in cells],
    )


@pytest.hookimpl(trylast=True)  # after -k/-m deselection: grid.json lists what will run
def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items) -> None:
    gs: GraftSession = config.stash[SESSION_KEY]
    gs.selected = []
    cells = []
    for item in items:
        params = getattr(getattr(item, "callspec", None), "params", {})
        cell = params.get("graft_cell", params.get("control_cell"))
        if isinstance(cell, CellSpec):
            gs.selected.append(cell.id)
            cells.append(cell)
    if gs.selected and not hasattr(config, "workerinput"):
        gs.store  # opens (creates, probes) the results dir: a one-line UsageError if it cannot
        check_writable("--report", gs.report_path.parent)
        gs.preflight(cells)
        gs.store.write_grid(gs.selected, gs.profile.name)


@pytest.fixture(scope="session")
def graft_session(request: pytest.FixtureRequest) -> GraftSession:
    return request.config.stash[SESSION_KEY]


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if hasattr(session.config, "workerinput"):
        return  # xdist worker: the controller builds the report from the shared store
    gs: GraftSession = session.config.stash.get(SESSION_KEY, None)
    if gs is None or not gs.selected:
        return
    try:
        path = gs.finish()
    except Exception as e:  # a report bug must not hide the cell results
        sys.stderr.write(f"\n[graftbench] REPORT.md not written: {type(e).__name__}: {e}\n")
        return
    if path is not None:
        gs.report_written = path


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    from bench.summary import summary_lines

    gs: GraftSession | None = config.stash.get(SESSION_KEY, None)
    if gs is None or not gs.selected or hasattr(config, "workerinput"):
        return
    terminalreporter.write_sep("-", "graftbench")
    for line in summary_lines(gs.profile.name, gs.profile.protocol.hash, gs.outcomes,
                              len(gs.selected), gs.results_dir, gs.report_path,
                              getattr(gs, "report_written", None) is not None):
        terminalreporter.write_line(line)
