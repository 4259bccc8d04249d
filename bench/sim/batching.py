"""How closed-loop episodes are run (not which): a value every layer passes down, free of torch
so the start-up check can build it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Batching:
    """How the planned episodes run, never which: `size` envs of a task at once in a gym vector
    env (`mode` "sync" or "async"; bench.sim.batched), or 1: one env in-process, stepped alone.
    The same episodes and rows whatever it is, so no episode log or record key holds it."""

    size: int = 1
    mode: str = "sync"

    def __post_init__(self) -> None:
        if self.size < 1:
            raise ValueError(f"rollout batch {self.size}: give envs per task >= 1")

    @property
    def label(self) -> str:
        return self.mode if self.size > 1 else "in-process"


IN_PROCESS = Batching()
