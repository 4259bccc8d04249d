"""The pytest plugin: hooks that hand work on to ONE `GraftSession` (bench.session), built at
`pytest_configure`: the grid parametrisation, collection, xdist scheduling, the session's end
(baseline, report) and the terminal summary. Options: bench.options.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from bench.grid.cells import (CellSpec, ScreenCase, control_cells, graft_cells, grid_cells,
                              screen_cases, staggered, tier_cells)
from bench.options import pytest_addoption  # noqa: F401  (the hook, found here by name)
from bench.session import GraftSession, Selection
from bench.startup import check_writable
from bench.summary import cell_id_of

SESSION_KEY = pytest.StashKey[GraftSession]()
DESELECTED_KEY = pytest.StashKey[list]()  # ids of grid cases that -k/-m deselected
GRID_MODULE = Path(__file__).with_name("test_grid.py")


def pytest_configure(config: pytest.Config) -> None:
    _configure_scale(config)
    session = GraftSession(config)  # the start-up check: a bad option is a UsageError here
    config.stash[SESSION_KEY] = session
    config.pluginmanager.register(session, "graftbench-session")  # its hook methods below


@pytest.hookimpl(wrapper=True)
def pytest_sessionstart(session: pytest.Session):
    """The start-up check's lines (folded duplicates, the camera rule's pairings), once, after
    the terminal's header."""
    result = yield
    gs: GraftSession | None = session.config.stash.get(SESSION_KEY, None)
    if gs is not None and not hasattr(session.config, "workerinput"):
        _write_lines(session.config, gs.startup_lines)
    return result


def _write_lines(config: pytest.Config, lines: list[str]) -> None:
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    for line in lines if reporter is not None else ():
        reporter.write_line(line)


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
    backbone_of = {c.id: c.backbone
                   for c in grid_cells(gs.profile, gs.screen_options is not None)}
    if gs.screen_options is not None:
        # A screen loads its backbone (normaliser, native grid), and the backbone's selection
        # reads every screen: screens go with the backbone's first group, ahead of its cells.
        backbone_of |= {c.id: c.backbone for c in screen_cases(gs.profile)}

    class BackboneScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            cell_id = cell_id_of(nodeid)
            if cell_id not in backbone_of:
                return nodeid
            # the cells the workers collected (pytest_xdist_node_collection_finished)
            selected = gs.selection.cells
            mine = [c for c in selected if backbone_of.get(c) == backbone_of[cell_id]]
            backbones = {backbone_of[c] for c in selected if c in backbone_of}
            groups = max(1, self.numnodes // max(1, len(backbones)))
            position = mine.index(cell_id) if cell_id in mine else 0
            return f"{backbone_of[cell_id]}:{position % groups}"

    return BackboneScheduling(config, log)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node, ids: list[str]) -> None:
    """xdist controller: it collects nothing itself, so the cells its workers collected (after
    -k/-m) are the selection that the paper preflight checks and grid.json and the report
    expect."""
    gs: GraftSession = node.config.stash[SESSION_KEY]
    if gs.selection.cells:
        return  # every worker collects the same items
    known = {c.id: c for c in grid_cells(gs.profile, gs.screen_options is not None)}
    screens = {c.id for c in screen_cases(gs.profile)} if gs.screen_options else set()
    case_ids = list(map(cell_id_of, ids))
    gs.collected(Selection(cells=tuple(c for c in case_ids if c in known),
                           screens=tuple(c for c in case_ids if c in screens)))
    if gs.selection.cells:
        try:  # the paper preflight of the selection, here where -k has been applied
            gs.preflight([known[c] for c in gs.selection.cells])
        except pytest.UsageError as e:  # raised inside xdist's loop: an exit, not an INTERNALERROR
            pytest.exit(f"ERROR: {e}", returncode=pytest.ExitCode.USAGE_ERROR)
        gs.store.write_grid(list(gs.selection.cells), gs.profile.name)


@pytest.hookimpl(tryfirst=True)
def pytest_pycollect_makeitem(collector, name: str, obj):
    """The grid's `test_screen` and `test_short_graft` exist only under --screen (no
    empty-parameter case without)."""
    if name in ("test_screen", "test_short_graft") and collector.path == GRID_MODULE:
        gs: GraftSession = collector.config.stash[SESSION_KEY]
        return [] if gs.screen_options is None else None
    if name == "test_control" and collector.path == GRID_MODULE:
        # --controls none: no case at all (an empty parametrisation showed test_control[NOTSET],
        # "1 skipped", in every such run).
        gs = collector.config.stash[SESSION_KEY]
        return [] if not control_cells(gs.profile) else None
    if name == "test_robust" and collector.path == GRID_MODULE:  # --robustness only
        gs = collector.config.stash[SESSION_KEY]
        return [] if not gs.profile.robustness else None
    return None


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    names = metafunc.fixturenames
    session: GraftSession = metafunc.config.stash[SESSION_KEY]
    # Every worker collects the same order (xdist checks); the controller collects nothing.
    workers = getattr(metafunc.config, "workerinput", {}).get("workercount", 1)
    if "screen_case" in names:  # --screen: before the grafts, in bench/test_grid.py's order
        metafunc.parametrize("screen_case", [
            pytest.param(c, id=c.id, marks=pytest.mark.xdist_group(c.backbone))
            for c in staggered(screen_cases(session.profile), workers)])
        return
    if "tier_cell" in names:  # --screen: the short grafts, after the screens
        metafunc.parametrize("tier_cell", [
            pytest.param(c, id=c.id, marks=pytest.mark.xdist_group(c.backbone))
            for c in staggered(tier_cells(session.profile), workers)])
        return
    if "robust_cell" in names:  # --robustness: after every cell, in bench/test_grid.py's order
        from bench.run.robust_run import robust_cells

        metafunc.parametrize("robust_cell", [
            pytest.param(c, id=c.id, marks=pytest.mark.xdist_group(c.backbone))
            for c in staggered(robust_cells(session.profile), workers)])
        return
    if "graft_cell" not in names and "control_cell" not in names:
        return
    if not hasattr(metafunc.config, "workerinput"):
        # A grid module outside bench/ (tests' own): checked here, at its collection.
        _write_lines(metafunc.config, session.check_names_once())
    cells = staggered(graft_cells(session.profile) if "graft_cell" in names
                      else control_cells(session.profile), workers)
    argname = "graft_cell" if "graft_cell" in names else "control_cell"
    metafunc.parametrize(
        argname,
        [pytest.param(c, id=c.id, marks=pytest.mark.xdist_group(c.backbone)) for c in cells],
    )


@pytest.hookimpl(trylast=True)  # after -k/-m deselection: grid.json lists what will run
def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items) -> None:
    gs: GraftSession = config.stash[SESSION_KEY]
    cells, screens, robust = [], [], []
    for item in items:
        params = getattr(getattr(item, "callspec", None), "params", {})
        cell = params.get("graft_cell", params.get("control_cell", params.get("tier_cell")))
        if isinstance(cell, CellSpec):
            cells.append(cell)
        elif isinstance(params.get("screen_case"), ScreenCase):
            screens.append(params["screen_case"].id)
        elif "robust_cell" in params:
            robust.append(params["robust_cell"].id)
    if not items and not hasattr(config, "workerinput"):
        _refuse_empty_selection(config)
    gs.collected(Selection(tuple(c.id for c in cells), tuple(screens), tuple(robust)))
    if (cells or screens) and not hasattr(config, "workerinput"):
        gs.store  # opened at start-up (bench/ runs), else here: a one-line UsageError if it cannot
        check_writable("--report", gs.report_path.parent)
        gs.preflight(cells)  # the selected cells' artifacts (after -k)
    if cells and not hasattr(config, "workerinput"):
        gs.store.write_grid([c.id for c in cells], gs.profile.name)


def pytest_deselected(items) -> None:
    grid = [item.nodeid for item in items if Path(str(item.path)) == GRID_MODULE]
    if grid:
        items[0].config.stash.setdefault(DESELECTED_KEY, []).extend(grid)


def _refuse_empty_selection(config: pytest.Config) -> None:
    """-k/-m that selects no grid case is a usage error with ids to pick from, not pytest's bare
    "no tests collected" (exit 5)."""
    deselected = config.stash.get(DESELECTED_KEY, [])
    if not deselected:
        return
    given = " ".join(f"{flag} {value!r}" for flag, value in
                     (("-k", config.getoption("keyword")), ("-m", config.getoption("markexpr")))
                     if value)
    examples = ", ".join(sorted({nodeid.rsplit("::", 1)[-1] for nodeid in deselected})[:3])
    raise pytest.UsageError(
        f"{given} selects none of the {len(deselected)} cases of this grid; ids read as the cell "
        f"(an encoder's ':' is written '_'), e.g. {examples}: pick words from them, or list "
        "them all with --collect-only -q")


@pytest.fixture(scope="session")
def graft_session(request: pytest.FixtureRequest) -> GraftSession:
    return request.config.stash[SESSION_KEY]


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if hasattr(session.config, "workerinput"):
        return  # xdist worker: the controller compares and reports from the shared store
    gs: GraftSession = session.config.stash.get(SESSION_KEY, None)
    if gs is None or not gs.selection:
        return
    try:
        sections = gs.finish_baseline()
    except Exception as e:  # a comparison that could not be made must not pass silently
        sys.stderr.write(f"\n[graftbench] baseline compare/save failed: {type(e).__name__}: {e}\n")
        session.exitstatus = pytest.ExitCode.INTERNAL_ERROR
        sections = []
    if gs.baseline.rank_flipped and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
    gs.finish(sections)
    if gs.report_error is not None and session.exitstatus == 0:  # never passes as a success
        session.exitstatus = pytest.ExitCode.INTERNAL_ERROR


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    from bench.summary import screen_summary_lines, summary_lines

    gs: GraftSession | None = config.stash.get(SESSION_KEY, None)
    selection = gs.selection if gs is not None else None
    if not (selection and (selection.cells or selection.screens)) or hasattr(config, "workerinput"):
        return
    terminalreporter.write_sep("-", "graftbench")
    lines = summary_lines(gs.profile.name, gs.profile.protocol.hash, gs.outcomes,
                          len(gs.selection.cells), gs.results_dir, gs.report_path,
                          gs.report_written is not None, gs.report_error)
    if gs.screening is not None:
        lines[2:2] = screen_summary_lines(gs.screening.outcomes, gs.screening.dropped)
    lines += [f"set aside: {line}" for line in gs.set_aside_lines]
    for line in lines:
        terminalreporter.write_line(line)
    gs.baseline.summary(terminalreporter)
