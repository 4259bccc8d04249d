"""The pytest plugin: hooks that hand work on to ONE `GraftSession` (bench.session), built at
`pytest_configure`: the grid parametrisation, collection, xdist scheduling (bench.scheduling),
the session's end (baseline, report) and the terminal summary. The hooks decide nothing: what
a selection starts, what the run's exit status is and what the summary says are the session's
(`collected`, `finish`, `display`). Options: bench.options.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.grid.cells import (CellSpec, ScreenCase, control_cells, graft_cells, grid_cells,
                              screen_cases, staggered, tier_cells)
from bench.options import pytest_addoption  # noqa: F401  (the hook, found here by name)
from bench.scheduling import backbone_scheduler, configure_scale, default_workers
from bench.session import GraftSession, Selection
from bench.summary import cell_id_of

SESSION_KEY = pytest.StashKey[GraftSession]()
DESELECTED_KEY = pytest.StashKey[list]()  # ids of grid cases that -k/-m deselected
GRID_MODULE = Path(__file__).with_name("test_grid.py")


@pytest.hookimpl(tryfirst=True)  # before xdist's, which turns -n into workers
def pytest_cmdline_main(config: pytest.Config) -> None:
    workers = default_workers(config)
    if workers is not None:
        config.option.numprocesses = workers


def pytest_configure(config: pytest.Config) -> None:
    configure_scale(config)
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


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    if config.getvalue("dist") != "loadgroup":
        return None
    return backbone_scheduler(config, log, config.stash[SESSION_KEY])


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
    try:  # the start of the run's ends, here where -k has been applied
        gs.collected(Selection(cells=tuple(c for c in case_ids if c in known),
                               screens=tuple(c for c in case_ids if c in screens),
                               sliced=not set(known) <= set(case_ids)),
                     [known[c] for c in case_ids if c in known])
    except pytest.UsageError as e:  # raised inside xdist's loop: an exit, not an INTERNALERROR
        pytest.exit(f"ERROR: {e}", returncode=pytest.ExitCode.USAGE_ERROR)


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
        from bench.robust.cases import robust_cells

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
    sliced = bool(config.stash.get(DESELECTED_KEY, []))
    gs.collected(Selection(tuple(c.id for c in cells), tuple(screens), tuple(robust), sliced),
                 cells)


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
    gs: GraftSession | None = session.config.stash.get(SESSION_KEY, None)
    if gs is not None:
        session.exitstatus = gs.finish(session.exitstatus)


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    gs: GraftSession | None = config.stash.get(SESSION_KEY, None)
    if gs is not None:
        gs.display(terminalreporter)
