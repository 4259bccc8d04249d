"""Closed loop beside offline MSE: success rates of rolled-out cells and rank agreement.

Per backbone x suite, the items are the cells that carry a `rollouts` entry, grouped over seeds by
what they are (graft encoder, control kind + encoder + variant, native). Each item has a mean
offline MSE (normalised, over seeds) and a mean success rate (over seeds). Agreement is measured
by bench.analysis.agreement (the one place, one tie rule) with predicted = -MSE (the offline
tier, higher is better) and actual = success rate (the closed loop): Kendall tau-b, weighted
tau, MMRV (SimplerEnv's, in success-rate units), top-1 regret (success points lost by taking the
offline winner) and Pearson r of -MSE and success. +1 (tau, r) means "the offline ranking is the
closed-loop ranking". A closed-loop ranking that is one tie (every item succeeds equally often)
has no order: those statistics are `Undefined` with the reason, never 0.

Intervals (stated in the report): a paired bootstrap. Each replicate draws every item's seeds,
the held-out episodes within their tasks and windows within a drawn episode, and, independently,
the rollout episodes within their task (identical init states across cells), n - 1 of n at each
level (bench.analysis.hierarchy), once for all items, and recomputes every statistic; percentile
interval over the replicates where it is defined. With a handful of items and few episodes the interval is wide: that is the
honest answer at small N.

Given the candidates (bench.analysis.candidates: the native policy and grafts of trained
encoders), the same agreement is computed again over the candidate items alone: telling working
items from failing ones is the easy half, ordering the plausible ones the question.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np

from bench.analysis.agreement import (
    Interval, Measure, Undefined, WITH_PEARSON, agreement, kendall_p_value, pearson_r,
)
from bench.analysis.two_axes import SeedStacks, bootstrap_two_axes
from bench.analysis.offline_measures import (MeasureAgreement, Rolled, full_chunk,
                                             measure_agreements, seed_stack)
from bench.analysis.hierarchy import Units
from bench.analysis.rankings import CONFIDENCE
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


def common_success(rollouts: dict, keys: list[tuple[int, int, int]]) -> list[float]:
    """A cell's success on the episodes `keys`, in that order."""
    success = {k: float(e["success"]) for k, e in zip(episode_keys(rollouts),
                                                        rollouts["episodes"])}
    return [success[k] for k in keys]


def _jsonable(value):
    if isinstance(value, Undefined):
        return {"undefined": value.reason}
    return asdict(value) if isinstance(value, Interval) else value


@dataclass
class ClosedLoop:
    """Offline vs closed-loop ranking of the rolled-out items of one backbone x suite.

    `agreement`: statistic name (WITH_PEARSON, plus "p_value" of Kendall's test) -> value or
    Undefined; `intervals`: the same names -> bootstrap Interval or Undefined."""

    backbone: str
    suite: str
    items: list[str] = field(default_factory=list)
    seeds: dict[str, list[int]] = field(default_factory=dict)
    mse: list[float] = field(default_factory=list)
    success: list[float] = field(default_factory=list)
    success_ci: list[tuple[float, float]] = field(default_factory=list)
    n_episodes: list[int] = field(default_factory=list)
    agreement: dict[str, Measure] = field(default_factory=dict)
    intervals: dict[str, Interval | Undefined] = field(default_factory=dict)
    n_resamples: int = 0
    missing: str | None = None
    # Every offline measure's agreement with success (bench.analysis.offline_measures).
    measures: list[MeasureAgreement] = field(default_factory=list)
    # The same agreement over the candidate items alone (empty: no candidate set given; a
    # "missing" key says why it was not computed).
    candidates: list[str] = field(default_factory=list)
    candidate_agreement: dict[str, Measure] = field(default_factory=dict)
    candidate_intervals: dict[str, Interval | Undefined] = field(default_factory=dict)
    # Episodes left out because not every rolled-out cell ran them (a sequential study runs
    # its later rounds on the items still open): the agreement is paired on the common ones.
    uncommon_episodes: int = 0
    # Paired episodes of the agreement over every item, and of the candidates' (their own
    # common episodes: a sequential study rolls the failing items out for fewer rounds).
    common_episodes: int = 0
    candidate_episodes: int = 0

    @property
    def measured(self) -> bool:
        """Agreement was computed (paired cells, at least two items)."""
        return bool(self.agreement)

    def interval_of(self, name: str) -> tuple[float, float] | None:
        """(low, high) of statistic `name`'s bootstrap interval; None when it has none."""
        ci = self.intervals.get(name)
        return (ci.low, ci.high) if isinstance(ci, Interval) else None

    def to_dict(self) -> dict:
        out = {k: v for k, v in asdict(self).items()
               if k not in ("agreement", "intervals", "measures")}
        out["measures"] = [m.to_dict() for m in self.measures]
        for name in ("agreement", "intervals", "candidate_agreement", "candidate_intervals"):
            out[name] = {k: _jsonable(v) for k, v in getattr(self, name).items()}
        return out

    def candidate_interval_of(self, name: str) -> tuple[float, float] | None:
        ci = self.candidate_intervals.get(name)
        return (ci.low, ci.high) if isinstance(ci, Interval) else None


def agreement_with_success(per_window: np.ndarray, per_episode: np.ndarray, seeds: SeedStacks,
                           n_resamples: int, random_seed: int, units: tuple[Units, Units]
                           ) -> tuple[dict[str, Measure], dict[str, Interval | Undefined]]:
    """(statistics, intervals) of -MSE against success over the rows given: per_window (I, W)
    MSE and per_episode (I, E) success, means over seeds; seeds: their per-seed stacks; units:
    how the windows (held-out episodes, tasks) and the rollout episodes (tasks) group."""
    predicted, actual = -per_window.mean(axis=1), per_episode.mean(axis=1)
    point = agreement(predicted, actual)
    stats = {k: pearson_r(predicted, actual) if k == "pearson_r" else getattr(point, k)
             for k in WITH_PEARSON}
    stats["p_value"] = kendall_p_value(predicted, actual)
    return stats, bootstrap_two_axes(-per_window, per_episode, n_resamples=n_resamples,
                                     seed=random_seed, confidence=CONFIDENCE, seeds=seeds,
                                     units=units)


def _on_candidates(out: ClosedLoop, per_window: np.ndarray, per_episode: np.ndarray,
                   seeds: SeedStacks, candidates: frozenset[str], random_seed: int,
                   units: tuple[Units, Units]) -> None:
    """The agreement again over the candidate items (rows of `per_window` in out.items' order)."""
    rows = np.array([i for i, item in enumerate(out.items) if item in candidates], dtype=int)
    out.candidates = [out.items[i] for i in rows]
    if len(rows) < 2:
        out.candidate_agreement = {"tau_b": Undefined(
            f"{len(rows)} candidate item(s) rolled out: fewer than 2, nothing to rank")}
        return
    kept = SeedStacks(seeds.predicted[rows], seeds.actual[rows], seeds.count[rows],
                      seeds.item[rows])
    out.candidate_agreement, out.candidate_intervals = agreement_with_success(
        per_window[rows], per_episode[rows], kept, out.n_resamples, random_seed, units)


def _paired(rolled: list, keys: list) -> Rolled:
    """The records' items (grouped over releases and seeds by label), paired on the episodes
    `keys`: each cell's success read once."""
    groups: dict[str, list] = {}
    for r in rolled:
        groups.setdefault(record_label(r), []).append(r)
    items = sorted(groups)
    success = [[common_success(g.run.rollouts, keys) for g in groups[i]] for i in items]
    return Rolled(items, groups, seed_stack(success), np.array([k[0] for k in keys]))


def common_keys(rolled: list) -> list[tuple[int, int, int]]:
    """The episodes (task, episode, init state) every record ran, in the first one's order."""
    common = set.intersection(*(set(episode_keys(r.run.rollouts)) for r in rolled))
    return [k for k in episode_keys(rolled[0].run.rollouts) if k in common]


def rollout_agreement(records: Sequence, backbone: str, suite: str, *,
                      n_resamples: int = DEFAULT_RESAMPLES, random_seed: int = 0,
                      candidates: frozenset[str] | None = None) -> ClosedLoop:
    """Agreement of offline MSE and success over the rolled-out cells of backbone x suite, and
    over the `candidates` (item labels) among them when given: on the episodes every candidate
    ran (more than every item ran when a sequential study rolled the failing ones out less)."""
    out = ClosedLoop(backbone, suite, n_resamples=n_resamples)
    rolled = [r for r in records if r.backbone == backbone and r.suite == suite
              and rolled_out(r)]
    if not rolled:
        out.missing = "no cell with rollouts (run with --rollouts N on a simulated suite)"
        return out
    keys = common_keys(rolled)
    out.uncommon_episodes = sum(len(r.run.rollouts["episodes"]) for r in rolled) - len(
        keys) * len(rolled)
    windows = rolled[0].scores.window_ids
    for r in rolled:
        if not keys or r.scores.window_ids != windows:
            out.missing = (f"{r.cell_id} was rolled out from other init states or scored on other "
                           "windows than the rest: not paired, no agreement computed")
            return out
    rolled_items = _paired(rolled, keys)
    out.items, groups = rolled_items.items, rolled_items.groups
    # The items' (I, W) MSE and (I, E) success are means over their seeds (full chunk, with its
    # seed stacks: bench.analysis.offline_measures).
    full = full_chunk(rolled_items)
    per_window, per_episode = full.errors, full.success
    out.seeds = {i: sorted(g.seed for g in groups[i]) for i in out.items}
    out.mse = per_window.mean(axis=1).tolist()
    out.success = per_episode.mean(axis=1).tolist()
    out.common_episodes = len(keys)
    for i, by_seed in zip(out.items, rolled_items.success_by_seed):
        n = len(keys) * len(groups[i])
        out.n_episodes.append(n)
        out.success_ci.append(wilson_interval(int(np.nansum(by_seed)), n))
    if len(out.items) < 2:
        out.missing = f"only one rolled-out item ({out.items[0]}): nothing to rank"
        return out
    units = rolled_items.units  # as the rankings draw; seeds per item: full.seeds
    out.agreement, out.intervals = agreement_with_success(per_window, per_episode, full.seeds,
                                                          n_resamples, random_seed, units)
    own = [r for r in rolled if candidates is not None and record_label(r) in candidates]
    own_keys = common_keys(own) if own else keys
    # The same pairing: the candidates' rows of the same draws; else their own episodes' below.
    same = candidates is not None and own_keys == keys
    out.measures = measure_agreements(rolled_items, candidates if same else None,
                                      n_resamples=n_resamples, seed=random_seed)
    if candidates is not None:
        out.candidate_episodes = len(own_keys)
        if same:
            _on_candidates(out, per_window, per_episode, full.seeds, candidates, random_seed,
                           units)
        else:
            _on_own_episodes(out, _paired(own, own_keys), random_seed)
    return out


def _on_own_episodes(out: ClosedLoop, cand: Rolled, random_seed: int) -> None:
    """The candidates' agreement (and each measure's) on the episodes every candidate ran."""
    out.candidates = list(cand.items)
    if len(cand.items) < 2:
        out.candidate_agreement = {"tau_b": Undefined(
            f"{len(cand.items)} candidate item(s) rolled out: fewer than 2, nothing to rank")}
        return
    full = full_chunk(cand)
    out.candidate_agreement, out.candidate_intervals = agreement_with_success(
        full.errors, full.success, full.seeds, out.n_resamples, random_seed, cand.units)
    own = measure_agreements(cand, n_resamples=out.n_resamples, seed=random_seed)
    by_name = {m.name: m for m in own}
    for m in out.measures:
        m.on_candidates = by_name.get(m.name)


def closed_loop_all(records: Sequence, **kwargs) -> list[ClosedLoop]:
    """One ClosedLoop per backbone x suite that has at least one rolled-out cell."""
    pairs = sorted({(r.backbone, r.suite) for r in records if rolled_out(r)})
    return [rollout_agreement(records, b, s, **kwargs) for b, s in pairs]
