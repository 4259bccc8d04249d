"""Closed loop beside offline MSE: success rates of rolled-out cells and rank agreement.

Per backbone x suite, the items are the cells that carry a `rollouts` entry, grouped over seeds by
what they are (graft encoder, control kind + encoder + variant, native). Each item has a mean
offline MSE (normalised, over seeds) and a mean success rate (over seeds). Agreement is Kendall
tau-b and weighted tau between the MSE ranking and the failure-rate ranking (1 - success), so
+1 means "the offline ranking is the closed-loop ranking".

Interval of tau (stated in the report): a paired bootstrap. Each replicate draws the held-out
windows and the rollout episodes (identical init states across cells) with replacement, once
for all items, and recomputes both rankings; percentile interval. With a handful of items and
a few episodes per task the interval is wide: that is the honest answer at small N.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np

from bench.analysis.agreement import as_float, kendall_tau_b
from bench.analysis.rankings import CONFIDENCE, PRIMARY
from bench.analysis.transfer import rank_agreement
from bench.grid.kinds import record_label
from bench.stats import wilson_interval

DEFAULT_RESAMPLES = 1000


def rolled_out(record) -> bool:
    """The record carries closed-loop episodes (not absent, not skipped)."""
    return bool((record.run.rollouts or {}).get("episodes"))


def episode_keys(rollouts: dict) -> list[tuple[int, int, int]]:
    """(task, episode, init_state) of every rolled-out episode, in stored order."""
    return [(int(e["task"]), int(e["episode"]), int(e.get("init_state", -1)))
            for e in rollouts["episodes"]]


@dataclass
class ClosedLoop:
    """Offline vs closed-loop ranking of the rolled-out items of one backbone x suite."""

    backbone: str
    suite: str
    items: list[str] = field(default_factory=list)
    seeds: dict[str, list[int]] = field(default_factory=dict)
    mse: list[float] = field(default_factory=list)
    success: list[float] = field(default_factory=list)
    success_ci: list[tuple[float, float]] = field(default_factory=list)
    n_episodes: list[int] = field(default_factory=list)
    agreement: dict = field(default_factory=dict)
    tau_ci: tuple[float, float] = (float("nan"), float("nan"))
    n_resamples: int = 0
    missing: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def _tau(mse: np.ndarray, success: np.ndarray) -> float:
    # a constant ranking has no order to agree with: undefined, NaN in the resample array
    return as_float(kendall_tau_b(-mse, success))


def rollout_agreement(records: Sequence[dict], backbone: str, suite: str, *,
                n_resamples: int = DEFAULT_RESAMPLES, random_seed: int = 0) -> ClosedLoop:
    """Agreement of offline MSE and success over the rolled-out cells of backbone x suite."""
    out = ClosedLoop(backbone, suite, n_resamples=n_resamples)
    rolled = [r for r in records if r.backbone == backbone and r.suite == suite
              and rolled_out(r)]
    if not rolled:
        out.missing = "no cell with rollouts (run with --rollouts N on a simulated suite)"
        return out
    keys = episode_keys(rolled[0].run.rollouts)
    windows = rolled[0].scores.window_ids
    for r in rolled:
        if episode_keys(r.run.rollouts) != keys or r.scores.window_ids != windows:
            out.missing = (f"{r.cell_id} was rolled out from other init states or scored on other "
                           "windows than the rest: not paired, no agreement computed")
            return out
    groups: dict[str, list[dict]] = {}
    for r in rolled:
        groups.setdefault(record_label(r), []).append(r)
    out.items = sorted(groups)
    # (I, W) per-window MSE and (I, E) per-episode success, each averaged over the item's seeds.
    per_window = np.array([np.mean([g.scores.per_window_in(PRIMARY) for g in groups[i]], axis=0)
                           for i in out.items])
    per_episode = np.array([np.mean([[float(e["success"]) for e in g.run.rollouts["episodes"]]
                                     for g in groups[i]], axis=0) for i in out.items])
    out.seeds = {i: sorted(g.seed for g in groups[i]) for i in out.items}
    out.mse = per_window.mean(axis=1).tolist()
    out.success = per_episode.mean(axis=1).tolist()
    for i in out.items:
        n = sum(len(g.run.rollouts["episodes"]) for g in groups[i])
        k = sum(bool(e["success"]) for g in groups[i] for e in g.run.rollouts["episodes"])
        out.n_episodes.append(n)
        out.success_ci.append(wilson_interval(k, n))
    if len(out.items) < 2:
        out.missing = f"only one rolled-out item ({out.items[0]}): nothing to rank"
        return out
    out.agreement = rank_agreement(out.mse, [1.0 - s for s in out.success])
    rng = np.random.default_rng(random_seed)
    taus = []
    for _ in range(n_resamples):
        w = rng.integers(0, per_window.shape[1], per_window.shape[1])
        e = rng.integers(0, per_episode.shape[1], per_episode.shape[1])
        taus.append(_tau(per_window[:, w].mean(axis=1), per_episode[:, e].mean(axis=1)))
    taus = np.asarray(taus)
    finite = taus[np.isfinite(taus)]
    out.agreement["resamples_with_a_tie_only"] = int(len(taus) - len(finite))
    if len(finite):
        alpha = (1 - CONFIDENCE) / 2
        out.tau_ci = (float(np.quantile(finite, alpha)), float(np.quantile(finite, 1 - alpha)))
    return out


def closed_loop_all(records: Sequence[dict], **kwargs) -> list[ClosedLoop]:
    """One ClosedLoop per backbone x suite that has at least one rolled-out cell."""
    pairs = sorted({(r.backbone, r.suite) for r in records if rolled_out(r)})
    return [rollout_agreement(records, b, s, **kwargs) for b, s in pairs]
