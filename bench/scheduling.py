"""How a run spreads over processes: `-n N` means `--dist loadgroup` with ONE backbone per xdist
worker (a 3.3B model loads once per worker), each worker's torch threads and GPU, and the
scheduler that groups the grid's cases by backbone. bench.plugin's hooks call these.
"""

from __future__ import annotations

import os

import pytest

from bench.grid.cells import grid_cells, screen_cases
from bench.summary import cell_id_of


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
    N workers work. (xdist's own loadgroup reads a nodeid suffix that pytest 9.2 no longer lets
    it add, pytest-dev/pytest-xdist#1386: it silently spread every backbone over all workers.)
    `gs`: the run's GraftSession (its profile, and the selection its workers collected)."""
    from xdist.scheduler import LoadScopeScheduling

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
            selected = gs.selection.cells
            mine = [c for c in selected if backbone_of.get(c) == backbone_of[cell_id]]
            backbones = {backbone_of[c] for c in selected if c in backbone_of}
            groups = max(1, self.numnodes // max(1, len(backbones)))
            position = mine.index(cell_id) if cell_id in mine else 0
            return f"{backbone_of[cell_id]}:{position % groups}"

    return BackboneScheduling(config, log)


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
