"""How closed-loop episodes are run (not which): a value every layer passes down, free of torch
so the start-up check can build it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Batching:
    """How the planned episodes run, never which: `size` envs of a task at once in a gym vector
    env (`mode` "sync" or "async"; bench.sim.batched), `workers` processes each stepping one env
    (bench.sim.workers), or one env in-process, stepped alone.
    The same episodes and rows whatever it is, so no episode log or record key holds it."""

    size: int = 1
    mode: str = "sync"
    # Worker processes, each stepping its own env one episode at a time (bench.sim.workers);
    # 1: the simulator runs in this process.
    workers: int = 1

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError(f"rollout batch {self.size}: give envs per task >= 1")
        if self.workers < 1:
            raise ValueError(f"rollout workers {self.workers}: give worker processes >= 1")
        if self.size > 1 and self.workers > 1:
            raise ValueError(f"rollout batch {self.size} with {self.workers} workers: choose "
                             "one (workers are the faster on a few CPU cores)")

    @property
    def label(self) -> str:
        if self.workers > 1:
            return f"{self.workers} workers"
        return self.mode if self.size > 1 else "in-process"


IN_PROCESS = Batching()
