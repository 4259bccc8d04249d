"""The run's memory at start-up (bench.memory) and the data-sized numbers (bench.data_bounds):
known answers of the estimate, the line printed above half the machine's memory, the refusal
when it cannot fit, and a batch order that no longer grows with the steps."""

from __future__ import annotations

import dataclasses
import itertools

import pytest

import backbones  # noqa: F401  (imported before pytester's sys.modules snapshot)
import encoders  # noqa: F401
import bench.memory
from bench.grid.protocol import PAPER, TINY
from bench.memory import FEATURE_BATCH_BYTES, GIB, PROCESS_BYTES, ROLLOUT_WORKER_BYTES, estimate
from tests.bench_inprocess import bench_run  # noqa: F401  (the fixture)
from tests.sim_marks import needs_libero
from tests.test_bad_inputs import assert_one_screen

pytest_plugins = ["pytester"]
# The tiny spatial suite held in memory: at most 4 tasks x 16 episodes x 50 frames, two cameras
# of 3 x 64 x 64 uint8 (bench.suites.synthetic).
TINY_SPATIAL_BYTES = 4 * 16 * 50 * 2 * 3 * 64 * 64


def test_the_estimate_of_the_tiny_grid_is_the_process_and_its_suite():
    one = estimate(TINY, 1)
    assert one.parts == (("process", PROCESS_BYTES), ("data", TINY_SPATIAL_BYTES))
    assert one.total == PROCESS_BYTES + TINY_SPATIAL_BYTES
    two = estimate(TINY, 2)  # two workers and the xdist controller
    assert two.total == 2 * (PROCESS_BYTES + TINY_SPATIAL_BYTES) + PROCESS_BYTES


def test_the_estimate_of_the_paper_grid_counts_a_worker_s_backbones():
    """Under -n 2 each worker takes one backbone's cells: the larger, pi0.5 (3.3e9 x 4 bytes)."""
    two = estimate(PAPER, 2)
    assert dict(two.parts)["1 backbone(s)"] == int(3.3e9 * 4)
    assert dict(two.parts)["data"] == FEATURE_BATCH_BYTES  # hub suites: read per batch
    one = estimate(PAPER, 1)  # one process loads both
    assert dict(one.parts)["2 backbone(s)"] == int(3.3e9 * 4) + int(450e6 * 4)


def test_kept_rollout_workers_count_for_each_measuring_process():
    plain = estimate(TINY, 2)
    kept = estimate(TINY, 2, rollout_workers=3)
    assert kept.parts == plain.parts + (("3 rollout workers", 3 * ROLLOUT_WORKER_BYTES),)
    assert kept.total == plain.total + 2 * 3 * ROLLOUT_WORKER_BYTES  # each of the 2 workers
    assert estimate(TINY, 2, rollout_workers=1) == plain  # the simulator in the process itself


@needs_libero  # --rollouts checks the simulator is installed before the memory
def test_a_rollout_run_whose_workers_cannot_fit_is_refused_naming_them(bench_run, monkeypatch):
    """The sim profile's run is 1.7 GB in one process; its 2 kept rollout workers add 3.8 GB."""
    monkeypatch.setattr(bench.memory, "machine_memory", lambda: (8 * GIB, 4 * GIB))
    # --co: refused at start-up all the same, and a run the check let through collects only
    out = bench_run("--profile", "sim", "--rollouts", "2", "--rollout-workers", "2", "--co")
    assert_one_screen(out, "memory: this run needs 5.5 GB at least (one process; a worker: "
                      "process 1.4 + data 0.3 + 2 rollout workers 3.8 GB), and 4.0 GB",
                      "fix: a smaller run or fewer rollout workers (--rollout-workers 1: the "
                      "simulator in-process)")
    assert not (bench_run.path / "results").exists()


def test_a_run_that_cannot_fit_is_refused_before_any_cell(bench_run, monkeypatch):
    monkeypatch.setattr(bench.memory, "machine_memory", lambda: (8 * GIB, 1 * GIB))
    out = bench_run()
    assert_one_screen(out, "memory: this run needs 1.5 GB at least (one process; a worker: "
                      "process 1.4 + data 0.1 GB), and 1.0 GB of the machine's 8.0 GB is "
                      "available; fix: a smaller run")
    assert not (bench_run.path / "results").exists()


def test_the_estimate_is_printed_above_half_the_machine(bench_run, monkeypatch):
    monkeypatch.setattr(bench.memory, "machine_memory", lambda: (2.5 * GIB, 2.4 * GIB))
    out = bench_run("--co", "-q", "--verbose")  # -q and --verbose: the terminal lines shown
    assert "[graftbench] memory: 1.5 GB at least (one process; a worker: process 1.4 + data " \
        "0.1 GB); the machine has 2.5 GB, 2.4 GB available" in out.screen, out.screen
    monkeypatch.setattr(bench.memory, "machine_memory", lambda: (4 * GIB, 4 * GIB))
    assert "[graftbench] memory" not in bench_run("--co", "-q", "--verbose").screen


def test_the_batch_order_is_streamed_whatever_the_steps():
    """Before: every step's indices were built up front; 10^11 steps ran out of memory."""
    from bench.loops.train import FitConfig, batch_order

    cfg = FitConfig(steps=10**11, batch_size=4, lr=1e-3, weight_decay=0.0, warmup_steps=0,
                    grad_clip=0.0, log_every=1)
    first = list(itertools.islice(batch_order(10, cfg, 0), 3))
    short = dataclasses.replace(cfg, steps=3)
    assert [t.tolist() for t in first] == [t.tolist() for t in batch_order(10, short, 0)]
