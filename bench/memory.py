"""A run's peak memory, estimated at start-up against the machine's (docs/SCALING.md, "Memory at
start-up"): printed when it is above half the machine's memory, refused when it exceeds the
memory available now (two xdist workers of a study held 7.7 and 5 GB; a `pytest -n 2` beside
them pushed a 24 GB machine into thrash).

The estimate, per process that measures cells (each xdist worker, or this one):

    PROCESS_BYTES                      torch, LeRobot and timm imported, a tiny release, a batch
  + its backbones' weights             hub releases: the cached model.safetensors' size, else
                                       parameters x 4 bytes (they load in fp32);
                                       your --policy folder: its *.safetensors bytes. Under -n
                                       a worker takes one backbone's cells (bench.scheduling):
                                       the largest ceil(backbones / workers) count
  + the data held                      suites decoded into memory (generated and simulated:
                                       frames x cameras x 3 x side^2 bytes, uint8); hub suites
                                       are read per batch; pooled features are read per batch
                                       from the store (FEATURE_BATCH_BYTES: its largest batch)

  + its rollout workers               `--rollout-workers W` beside --rollouts: W spawned simulator
                                       processes a measuring process keeps between its cells
                                       (ROLLOUT_WORKER_BYTES each)

times the workers, plus one PROCESS_BYTES for the xdist controller. It is a floor, not a bound:
activations beyond a batch's, encoders built in the loop and the allocator's slack come on top
(the real study's processes peaked at 5.6-7.9 GB where it says 1.7 GB), so a refusal means the
run cannot fit, and a printed estimate is the least it will take.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

GIB = 2**30
# Measured: the tiny grid's cell processes peaked at 1.35-1.37 GB RSS (REPORT_cells.csv,
# peak_memory_mb); torch, LeRobot and timm imported alone: 1.1 GB.
PROCESS_BYTES = int(1.4 * GIB)
# docs/SCALING.md: the largest batch of stored features read (pool_double of SigLIP on pi0.5).
FEATURE_BATCH_BYTES = 260 * 2**20
CAMERAS = 2  # LIBERO's two cameras (bench.suites: IMAGE_KEYS)
# Measured (docs/PERFORMANCE.md, "Closed-loop rollouts"): a kept rollout worker holding one
# LIBERO env at 128 px, 1.9 GB private (PSS 2.0 GB).
ROLLOUT_WORKER_BYTES = int(1.9 * GIB)


@dataclass(frozen=True)
class MemoryEstimate:
    """The parts one worker holds (what, bytes) and how many workers hold them."""

    workers: int
    parts: tuple[tuple[str, int], ...]

    @property
    def per_worker(self) -> int:
        return sum(b for _, b in self.parts)

    @property
    def total(self) -> int:
        return self.workers * self.per_worker + (PROCESS_BYTES if self.workers > 1 else 0)

    def text(self) -> str:
        parts = " + ".join(f"{what} {b / GIB:.1f}" for what, b in self.parts)
        workers = (f"{self.workers} workers x {self.per_worker / GIB:.1f} GB + the controller "
                   f"{PROCESS_BYTES / GIB:.1f}" if self.workers > 1 else "one process")
        return f"{self.total / GIB:.1f} GB at least ({workers}; a worker: {parts} GB)"


def backbone_bytes(profile, name: str) -> int:
    """Bytes of one backbone's weights while it loads (0: the tiny releases, in PROCESS_BYTES)."""
    policies = dict(profile.policies)
    if name in policies:
        folder = Path(policies[name].split("@")[0]).expanduser()
        return sum(p.stat().st_size for p in folder.glob("*.safetensors")) if folder.is_dir() else 0
    if profile.source != "hub":
        return 0
    from backbones import BACKBONES
    from ondisk.hubcache import cached_file

    entry = BACKBONES.get(name)
    if entry is None:
        return 0
    # The checkpoint the cache holds, as it is (the offline hub world's are tiny); the registry's
    # nominal size only when the cache has none yet (the preflight then names what is missing).
    weights = cached_file(entry.repo_id, "model.safetensors", entry.revision)
    if weights is not None and weights.is_file():
        return weights.stat().st_size
    return int(entry.params * 4) if entry.params != float("inf") else 0


def data_bytes(profile, suite: str) -> int:
    """Bytes of a suite's images held in memory (0: read per batch, or its size unknown)."""
    from bench.data_bounds import suite_size, training_frames

    if suite in dict(profile.datasets) or profile.data_source == "hub":
        return 0
    size = suite_size(profile, suite)
    if size is None:
        return 0
    frames = training_frames(size, 0, suite, profile) or 0  # held-out 0: every episode
    if profile.data_source == "sim":
        from bench.sim.demos import demo_spec

        side = demo_spec(suite, profile.sim_tasks, profile.sim_demos).image_size
    else:
        from bench.suites.synthetic import IMAGE_SIZE as side
    return frames * CAMERAS * 3 * side * side


def estimate(profile, workers: int, rollout_workers: int = 0) -> MemoryEstimate:
    """The run's estimate (module docstring) for `workers` processes measuring cells, each
    keeping `rollout_workers` simulator processes (0 or 1: the simulator runs in-process)."""
    parts = [("process", PROCESS_BYTES)]
    held = -(-len(profile.backbones) // max(1, workers))  # backbones a worker loads
    weights = sum(sorted((backbone_bytes(profile, b) for b in profile.backbones),
                         reverse=True)[:held])
    if weights:
        parts.append((f"{held} backbone(s)", weights))
    data = sum(data_bytes(profile, s) for s in profile.suites)
    if profile.source == "hub":
        data += FEATURE_BATCH_BYTES
    if data:
        parts.append(("data", data))
    if rollout_workers > 1:
        parts.append((f"{rollout_workers} rollout workers", rollout_workers * ROLLOUT_WORKER_BYTES))
    return MemoryEstimate(max(1, workers), tuple(parts))


def measuring_processes(config: pytest.Config, options) -> int:
    """Processes that measure cells on this machine: xdist's -n (resolved by its
    pytest_cmdline_main before the session starts), else one; a job array's tasks run
    elsewhere, one cell each."""
    n = getattr(config.option, "numprocesses", None)
    return n if isinstance(n, int) and n > 0 and options.executor == "local" else 1


def machine_memory() -> tuple[int, int]:
    """(total, available now) bytes of this machine from /proc/meminfo; (0, 0) when unknown."""
    try:
        fields = dict(line.split(":", 1) for line in Path("/proc/meminfo").read_text().splitlines())
        kib = {k: int(v.split()[0]) * 1024 for k, v in fields.items()
               if k in ("MemTotal", "MemAvailable")}
        return kib["MemTotal"], kib["MemAvailable"]
    except (OSError, ValueError, KeyError):
        return 0, 0


def check_memory(profile, workers: int, workers_option: str,
                 rollout_workers: int = 0) -> list[str]:
    """The estimate's line when above half the machine's memory; a UsageError when it exceeds
    the memory available now (nothing measured yet)."""
    total, available = machine_memory()
    if not total:
        return []
    run = estimate(profile, workers, rollout_workers)
    if run.total > available:
        fit = (available - PROCESS_BYTES) // run.per_worker  # workers beside the controller
        fewer = f"fewer workers ({workers_option} {fit})" if 1 <= fit < workers else "a smaller run"
        if rollout_workers > 1:
            fewer += " or fewer rollout workers (--rollout-workers 1: the simulator in-process)"
        raise pytest.UsageError(
            f"memory: this run needs {run.text()}, and {available / GIB:.1f} GB of the machine's "
            f"{total / GIB:.1f} GB is available; fix: {fewer}, fewer backbones (--backbones), "
            "or free memory first")
    if run.total > total / 2:
        return [f"[graftbench] memory: {run.text()}; the machine has {total / GIB:.1f} GB, "
                f"{available / GIB:.1f} GB available"]
    return []
