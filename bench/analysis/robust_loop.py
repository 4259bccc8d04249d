"""The robustness tier in closed loop: each rolled-out cell's success under every perturbation
beside its clean success, with Wilson 95% intervals, and the episodes the perturbation lost and
gained (the same episodes, paired by task and episode index: bench.robust.closed_loop). Pure
functions of stored records."""

from __future__ import annotations

from dataclasses import dataclass, field

from bench.results.record import Record
from bench.results.robust import RobustRecord
from bench.stats import wilson_interval


@dataclass(frozen=True)
class Rate:
    """Successes out of episodes, with the Wilson 95% interval."""

    successes: int
    episodes: int

    @property
    def rate(self) -> float:
        return self.successes / self.episodes if self.episodes else float("nan")

    @property
    def ci(self) -> tuple[float, float]:
        return tuple(wilson_interval(self.successes, self.episodes))


@dataclass
class LoopRow:
    """One cell: clean success and, per perturbation ("kind:severity"), the perturbed success
    and the paired episodes lost (clean success, perturbed failure) and gained."""

    cell_id: str
    backbone: str
    suite: str
    clean: Rate | None  # None: the cell's record holds no rollouts
    perturbed: dict[str, Rate] = field(default_factory=dict)
    lost: dict[str, int] = field(default_factory=dict)
    gained: dict[str, int] = field(default_factory=dict)


def _outcomes(rollouts: dict | None) -> dict[tuple[int, int], bool]:
    return {(int(e["task"]), int(e["episode"])): bool(e["success"])
            for e in (rollouts or {}).get("episodes", [])}


def closed_loop_rows(records: list[Record], robust: list[RobustRecord]) -> list[LoopRow]:
    """A LoopRow per current robustness record with rollouts (stale ones left out), in
    backbone, suite, cell order."""
    by_id = {r.cell_id: r for r in records}
    rows = []
    for rr in sorted(robust, key=lambda r: (r.backbone, r.suite, r.cell_id)):
        record = by_id.get(rr.cell_id)
        if not rr.rollouts or record is None or not rr.is_for(record):
            continue
        clean = _outcomes(record.run.rollouts)
        row = LoopRow(rr.cell_id, rr.backbone, rr.suite,
                      Rate(sum(clean.values()), len(clean)) if clean else None)
        for label, done in rr.rollouts.items():
            seen = _outcomes(done)
            row.perturbed[label] = Rate(sum(seen.values()), len(seen))
            paired = [k for k in seen if k in clean]
            row.lost[label] = sum(clean[k] and not seen[k] for k in paired)
            row.gained[label] = sum(seen[k] and not clean[k] for k in paired)
        rows.append(row)
    return rows
