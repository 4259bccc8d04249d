"""How a run spreads over processes: `-n N` means `--dist loadgroup` with ONE backbone per xdist
worker (a 3.3B model loads once per worker), each worker's torch threads and GPU, and the
scheduler that groups the grid's cases by backbone. Without -n, a run of the tiny world takes
both cores (`default_workers`). bench.plugin's hooks call these.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Mapping

import pytest

from bench.grid.cells import grid_cells, screen_cases
from bench.summary import cell_id_of
from ondisk.paths import REPO_ROOT

# Workers a tiny-world run takes when -n is not given: the 2 cores of the machine class the
# default run is sized for. Each worker is one torch thread (worker_threads), so a record's bits
# do not depend on the load at start (a serial run takes the CPUs the load leaves free, and
# 2 threads give other last bits than 1). More: -n N; one process: -n 0.
DEFAULT_WORKERS = 2


def default_workers(config: pytest.Config) -> int | None:
    """xdist workers for a `pytest bench` run given no -n (None: leave it to xdist, one process):
    min(CPUs, DEFAULT_WORKERS, what the memory available holds: bench.memory) when the run
    measures cells of the tiny world here. Not for the
    hub world (a GPU run chooses its -n), your own --policy, the simulator's suites, a job array,
    --collect-only, --pdb, a run of anything but the grid, or an xdist worker itself."""
    if (getattr(config.option, "numprocesses", "absent") is not None  # given, or no xdist
            or hasattr(config, "workerinput") or config.getoption("collectonly")
            or config.getoption("usepdb") or config.getoption("--executor") != "local"
            or config.getoption("--policy") or not _runs_the_grid(config)):
        return None
    from bench.grid.gridfile import base_profile_of
    from bench.grid.protocol import PROFILES

    grid = config.getoption("--grid")
    name = config.getoption("--profile") or (base_profile_of(grid) if grid else None) or "tiny"
    profile = PROFILES.get(name)
    if profile is None or profile.source != "tiny" or profile.suite_source is not None:
        return None  # an unknown name is the session's to refuse
    from bench.memory import estimate, machine_memory

    workers = min(len(os.sched_getaffinity(0)), DEFAULT_WORKERS)
    _, available = machine_memory()  # fewer workers where their memory is not there (0: unknown)
    while workers > 1 and available and estimate(profile, workers).total > available:
        workers -= 1
    return workers if workers > 1 else None


def _runs_the_grid(config: pytest.Config) -> bool:
    """Do the run's paths select bench/'s grid module (`pytest bench`, `bench/test_grid.py::...`)?"""
    grid = REPO_ROOT / "bench"
    for arg in config.args:
        path = (Path(config.invocation_params.dir) / arg.split("::")[0]).resolve()
        if path == grid or grid in path.parents:
            return True
    return False


def configure_scale(config: pytest.Config) -> None:
    """`-n N` implies `--dist loadgroup`; an xdist worker takes GPU (worker index mod GPU count)
    when GPUs exist, and its share of the CPUs as torch threads."""
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


def backbone_scheduler(config: pytest.Config, log, gs):
    """loadgroup by backbone, read from the cell id: each worker holds ONE backbone. With more
    workers than backbones, a backbone's cells are dealt round-robin into N // B groups so all
    N workers work. In the tiny world (`cell_units`) cells go out one unit at a time instead.
    (xdist's own loadgroup reads a nodeid suffix that pytest 9.2 no longer lets it add,
    pytest-dev/pytest-xdist#1386: it silently spread every backbone over all workers.)
    `gs`: the run's GraftSession (its profile, and the selection its workers collected)."""
    from xdist.scheduler import LoadScopeScheduling

    backbone_of = {c.id: c.backbone
                   for c in grid_cells(gs.profile, gs.screen_options is not None)}
    if gs.screen_options is not None:
        # A screen loads its backbone (normaliser, native grid), and the backbone's selection
        # reads every screen: screens go with the backbone's first group, ahead of its cells.
        backbone_of |= {c.id: c.backbone for c in screen_cases(gs.profile)}
    # At the first split, when the workers' selection (which the packs are drawn from) is known.
    units = functools.cache(
        lambda: cell_units(gs.profile, gs.screen_options is not None, gs.pack_units()))

    class BackboneScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            cell_id = cell_id_of(nodeid)
            if cell_id not in backbone_of:
                return nodeid
            if units() is not None:
                return units().get(cell_id, cell_id)
            selected = gs.selection.cells
            mine = [c for c in selected if backbone_of.get(c) == backbone_of[cell_id]]
            backbones = {backbone_of[c] for c in selected if c in backbone_of}
            groups = max(1, self.numnodes // max(1, len(backbones)))
            position = mine.index(cell_id) if cell_id in mine else 0
            return f"{backbone_of[cell_id]}:{position % groups}"

    return BackboneScheduling(config, log)


def cell_units(profile, screening: bool, packs: Mapping[str, str] | None = None
               ) -> dict[str, str] | None:
    """{cell id: its unit} for a grid of the tiny world, whose releases load in a second: each
    cell is a unit of its own, but for the controls that take their graft's trained projector,
    which go with that graft (bench.cell.plan.shared_projector_key), and the cells of one pack
    (`packs`, --pack-grafts: bench.cell.pack_run.pack_units), which go together. xdist hands the
    units out as workers free up, so the cores stay busy to the end (one backbone per worker
    left the SmolVLA worker idle while the pi0.5 one, ~1.5x slower a cell, finished; a screened
    study's cells dealt round-robin in two fixed halves left one core idle for its last 25
    minutes; packs kept on their backbone's worker left one idle for 14). Screens and short
    grafts too: a selection reads every screen of its backbone, and one that another worker is
    measuring is waited for under its lock, then resumed. None (group by backbone): the hub
    world (a worker holds one real backbone) or the robustness tier (a case reads its stored
    cell)."""
    from bench.cell.plan import shared_projector_key

    if not units_per_cell(profile):
        return None
    packs = packs or {}
    units = {}
    for cell in grid_cells(profile, screening):
        shared = shared_projector_key(cell, "cache")
        own = shared[0] if shared is not None else cell.id  # a control: its graft's
        units[cell.id] = packs.get(own, own)
    return units


def units_per_cell(profile) -> bool:
    """Does a run of `profile` hand its cells out one unit at a time (`cell_units`)?"""
    return profile.source == "tiny" and not profile.robustness


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
