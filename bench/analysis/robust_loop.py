"""The robustness tier in closed loop: each rolled-out cell's success under every perturbation
beside its clean success, with Wilson 95% intervals, and the episodes the perturbation lost and
gained (the same episodes, paired by task and episode index: bench.robust.closed_loop). Pure
functions of stored records."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bench.analysis.agreement import Interval, Measure, Undefined, kendall_tau_b
from bench.analysis.two_axes import SeedStacks, bootstrap_two_axes
from bench.analysis.offline_measures import seed_stack
from bench.analysis.rankings import PRIMARY
from bench.grid.kinds import record_label
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


@dataclass
class RobustOrder:
    """Under one perturbation ("kind:severity") of one backbone x suite: the rolled-out items'
    offline MSE on the robustness windows, clean and perturbed, beside their success, clean and
    perturbed (means over each item's seeds), and whether the offline robustness ranking (lower
    perturbed MSE first) predicts the closed-loop one (higher perturbed success first): Kendall
    tau-b over the items with the closed loop's paired bootstrap (each item's seeds, then the
    windows and the episodes drawn: bench.analysis.two_axes.bootstrap_two_axes)."""

    backbone: str
    suite: str
    label: str
    items: list[str] = field(default_factory=list)
    seeds: dict[str, list[int]] = field(default_factory=dict)
    clean_mse: list[float] = field(default_factory=list)
    mse: list[float] = field(default_factory=list)
    clean_success: list[float] = field(default_factory=list)
    success: list[float] = field(default_factory=list)
    episodes: list[int] = field(default_factory=list)
    tau_b: Measure | None = None
    interval: Interval | Undefined | None = None
    missing: str | None = None


def _item_stacks(pairs: list, label: str, windows: list[int], keys: list
                 ) -> tuple[list, list, list, list]:
    """Per seed of one item: clean and perturbed per-window MSE on `windows`, clean and
    perturbed per-episode success in `keys`' order."""
    clean_w, pert_w, clean_e, pert_e = [], [], [], []
    for record, rr in pairs:
        at = dict(zip(record.scores.window_ids, record.scores.per_window_in(PRIMARY)))
        clean_w.append([at[w] for w in windows])
        entry = next(e for e in rr.entries if e.label == label)
        pert_w.append(list(entry.per_window[PRIMARY]))
        clean, seen = _outcomes(record.run.rollouts), _outcomes(rr.rollouts[label])
        clean_e.append([float(clean[k]) for k in keys])
        pert_e.append([float(seen[k]) for k in keys])
    return clean_w, pert_w, clean_e, pert_e


def robust_orders(records: list[Record], robust: list[RobustRecord], *, n_resamples: int,
                  seed: int = 0) -> list[RobustOrder]:
    """A RobustOrder per backbone x suite x perturbation rolled out (current records only)."""
    by_id = {r.cell_id: r for r in records}
    groups: dict[tuple, dict[str, list]] = {}
    for rr in robust:
        record = by_id.get(rr.cell_id)
        if not rr.rollouts or record is None or not rr.is_for(record):
            continue
        for label in rr.rollouts:
            if any(e.label == label for e in rr.entries) and record.run.rollouts:
                groups.setdefault((rr.backbone, rr.suite, label), {}).setdefault(
                    record_label(record), []).append((record, rr))
    return [_order(key, items, n_resamples, seed) for key, items in sorted(groups.items())]


def _order(key: tuple, items: dict[str, list], n_resamples: int, seed: int) -> RobustOrder:
    out = RobustOrder(*key)
    pairs = [p for name in sorted(items) for p in items[name]]
    windows = pairs[0][1].window_ids
    keys = sorted(_outcomes(pairs[0][1].rollouts[out.label]))
    for record, rr in pairs:
        if rr.window_ids != windows or sorted(_outcomes(rr.rollouts[out.label])) != keys \
                or not set(keys) <= set(_outcomes(record.run.rollouts)):
            out.missing = (f"{record.cell_id} was scored on other windows or rolled out on other "
                           "episodes than the rest: not paired")
            return out
    out.items = sorted(items)
    stacks = [_item_stacks(items[name], out.label, windows, keys) for name in out.items]
    out.seeds = {name: sorted(r.seed for r, _ in items[name]) for name in out.items}
    # Each of the four: per item, the mean over its seeds of the mean over windows/episodes.
    out.clean_mse, out.mse, out.clean_success, out.success = (
        [float(np.mean([np.mean(per_seed) for per_seed in s[part]])) for s in stacks]
        for part in range(4))
    out.episodes = [len(keys) * len(items[name]) for name in out.items]
    if len(out.items) < 2:
        out.missing = f"only one rolled-out item ({out.items[0]}): nothing to rank"
        return out
    pert_w, pert_e = seed_stack([s[1] for s in stacks]), seed_stack([s[3] for s in stacks])
    out.tau_b = kendall_tau_b(-np.asarray(out.mse), np.asarray(out.success))
    seeds = SeedStacks(-pert_w, pert_e, np.array([len(items[n]) for n in out.items]),
                       np.arange(len(out.items)))
    out.interval = bootstrap_two_axes(-np.nanmean(pert_w, axis=1), np.nanmean(pert_e, axis=1),
                                      n_resamples=n_resamples, seed=seed, statistics=("tau_b",),
                                      seeds=seeds)["tau_b"]
    return out
