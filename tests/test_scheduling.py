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
from bench.cell.pack_run import candidates, pack_units
from bench.grid.cells import grid_cells
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


def test_the_hub_world_and_robustness_keep_a_backbone_per_worker():
    assert scheduling.cell_units(PAPER, screening=False) is None
    robust = dataclasses.replace(TINY, robustness=("brightness:1",))
    assert scheduling.cell_units(robust, screening=False) is None


def test_tiny_packs_go_out_as_units_of_k_cells_of_one_release():
    """--pack-grafts K in the tiny world: a backbone x suite x release's packable cells, K at a
    time in run order, are one unit each (not the backbone's: that kept a backbone's packs on one
    worker), a control with its graft's pack; a lead's mates are its unit's alone, and a cell
    stored when the units were drawn leads no pack."""
    cells = grid_cells(with_overrides(TINY, seeds=(0, 1), releases_per_backbone=2), False)
    packs = pack_units(cells, 3, "cache")
    units = scheduling.cell_units(with_overrides(TINY, seeds=(0, 1), releases_per_backbone=2),
                                  screening=False, packs=packs)
    by_unit: dict[str, list[str]] = {}
    for cell in cells:
        if cell.backbone == "smolvla":
            by_unit.setdefault(units[cell.id], []).append(cell.id.removeprefix("smolvla-spatial-"))
    packed = {u: ids for u, ids in by_unit.items() if u.startswith("pack:")}
    assert sorted(packed.values()) == [  # grafts 3 at a time, a release apart; the pixels
        ["dinov2_s-rel1-seed0", "dinov2_s-rel1-seed1", "pixels-rel1-seed0",  # controls with
         "pixels-shuffled_image-rel1-seed0"],  # their graft
        ["dinov2_s-seed0", "dinov2_s-seed1", "pixels-seed0", "pixels-shuffled_image-seed0"],
        ["native_wrapped-rel1-seed0", "native_wrapped-rel1-seed1"],
        ["native_wrapped-seed0", "native_wrapped-seed1"],
        ["pixels-rel1-seed1", "blind-rel1-seed0", "blind-rel1-seed1",
         "pixels-shuffled_image-rel1-seed1"],
        ["pixels-seed1", "blind-seed0", "blind-seed1", "pixels-shuffled_image-seed1"],
    ], packed
    assert by_unit["smolvla-spatial-native-seed0"] == ["native-seed0"]  # trains nothing: alone

    lead = cells[0]  # smolvla-spatial-dinov2_s-seed0
    assert [c.id for c in candidates(lead, cells, packs)] == [c.id for c in cells[:3]]
    assert len(candidates(lead, cells, None)) == 28  # not units: all of its backbone x suite
    assert candidates(lead, cells, pack_units(cells[1:], 3, "cache")) == []  # lead stored
