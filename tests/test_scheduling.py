"""How a run spreads over processes (bench.scheduling): a tiny-world `pytest bench` given no -n
takes both cores, nothing else does; in the tiny world cells go to workers one unit at a time,
a control that takes its graft's projector with that graft. That the default run's records equal
a one-process run's: tests/test_xdist.py, whose parallel run is the default's."""

from __future__ import annotations

import dataclasses
import os
from types import SimpleNamespace

import pytest

from bench import scheduling
from bench.grid.protocol import PAPER, TINY, TINY_FULL, with_overrides
from ondisk.paths import REPO_ROOT


def config(*args: str, cwd=REPO_ROOT, worker: bool = False, **options):
    """What default_workers reads of a pytest Config: `pytest ARGS` run in `cwd` (default: the
    repository) with `options` by their pytest names (numprocesses: None when -n is not given)."""
    given = {"collectonly": False, "usepdb": False, "--executor": "local", "--policy": None,
             "--grid": None, "--profile": None, **options}
    fake = SimpleNamespace(option=SimpleNamespace(numprocesses=given.pop("numprocesses", None)),
                           getoption=given.__getitem__, args=list(args),
                           invocation_params=SimpleNamespace(dir=cwd))
    if worker:
        fake.workerinput = {"workerid": "gw0"}
    return fake


@pytest.fixture
def cpus(monkeypatch):
    def set_cpus(n: int) -> None:
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(n)))
    set_cpus(2)
    return set_cpus


def test_the_tiny_grid_takes_both_cores_without_n(cpus):
    assert scheduling.default_workers(config("bench")) == 2
    assert scheduling.default_workers(config("bench/test_grid.py::test_graft")) == 2
    assert scheduling.default_workers(config("test_grid.py", cwd=REPO_ROOT / "bench")) == 2
    assert scheduling.default_workers(config("bench", **{"--profile": "tiny-full"})) == 2
    cpus(8)
    assert scheduling.default_workers(config("bench")) == scheduling.DEFAULT_WORKERS == 2
    cpus(1)
    assert scheduling.default_workers(config("bench")) is None


def test_two_workers_only_where_their_memory_is(cpus, monkeypatch):
    from bench import memory

    two = memory.estimate(TINY, 2).total
    monkeypatch.setattr(memory, "machine_memory", lambda: (2 * two, two))
    assert scheduling.default_workers(config("bench")) == 2
    monkeypatch.setattr(memory, "machine_memory", lambda: (2 * two, two - 1))
    assert scheduling.default_workers(config("bench")) is None  # one process: it fits alone


@pytest.mark.parametrize("case", [
    config("bench", numprocesses=0),  # -n 0: one process, asked for
    config("bench", numprocesses=3),  # -n 3: xdist's as given
    config("tests"), config(),  # the tests, or pyproject's testpaths
    config("bench", **{"--profile": "paper"}),  # the hub world: a GPU run picks its -n
    config("bench", **{"--profile": "sim"}),  # the simulator's suites
    config("bench", **{"--policy": ["mine=/some/folder"]}),
    config("bench", **{"--executor": "slurm"}),
    config("bench", collectonly=True), config("bench", usepdb=True),
    config("bench", worker=True),  # an xdist worker itself
], ids=["n0", "n3", "tests", "testpaths", "paper", "sim", "policy", "slurm", "collect-only",
        "pdb", "worker"])
def test_everything_else_keeps_what_it_asked_for(case, cpus):
    assert scheduling.default_workers(case) is None


def test_a_grid_file_counts_by_its_base_profile(tmp_path, cpus):
    for profile, expected in (("paper", None), ("tiny-full", 2)):
        grid = tmp_path / f"{profile}.toml"
        grid.write_text(f'profile = "{profile}"\n')
        assert scheduling.default_workers(config("bench", **{"--grid": str(grid)})) == expected


def test_tiny_cells_go_out_one_unit_at_a_time_a_control_with_its_graft():
    units = scheduling.cell_units(with_overrides(TINY, seeds=(0, 1)), screening=False)
    assert len(units) == 28 and len(set(units.values())) == 24
    for seed in (0, 1):
        for backbone in ("smolvla", "pi05"):
            graft = f"{backbone}-spatial-pixels-seed{seed}"
            assert units[f"{backbone}-spatial-pixels-shuffled_image-seed{seed}"] == graft
            assert units[f"{backbone}-spatial-native_wrapped-seed{seed}"] != graft
    assert scheduling.cell_units(TINY_FULL, screening=False) is not None
    # A screened tiny grid too: its short grafts are units of their own (the screens, not grid
    # cells, are their own unit by their id: bench.scheduling.backbone_scheduler).
    screened = scheduling.cell_units(TINY, screening=True)
    assert len(screened) > len(scheduling.cell_units(TINY, screening=False))
    assert screened["smolvla-spatial-pixels-short_1_8-seed0"] == "smolvla-spatial-pixels-short_1_8-seed0"


def test_the_hub_world_robustness_and_packs_keep_a_backbone_per_worker():
    assert scheduling.cell_units(PAPER, screening=False) is None
    assert scheduling.cell_units(TINY, screening=False, pack_grafts=2) is None
    robust = dataclasses.replace(TINY, robustness=("brightness:1",))
    assert scheduling.cell_units(robust, screening=False) is None
