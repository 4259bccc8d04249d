"""Offline measures beside the full-chunk MSE, each against closed-loop success.

Every measure is computed from what a cell record keeps (no retraining) and is one entry of
MEASURES: a name, a one-line definition and a function that turns the rolled-out items of one
backbone x suite (`Rolled`) into rows to rank: per-window errors (lower is better) and
per-episode successes, with masks when a row reads only some windows and episodes. A record
without what a measure reads leaves that measure "not measured" (with the reason), never 0.

Agreement of each measure with success uses the closed loop's statistics and bootstrap
(bench.analysis.agreement; rollouts.py's -MSE table): predicted = -error, actual = success;
Kendall tau-b, Spearman, Pearson, MMRV, top-1 regret; each replicate draws the held-out windows
and, independently, the rollout episodes with replacement, once for all rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from bench.analysis.agreement import BY_NAME, Interval, Measure, Undefined, percentile_intervals
from bench.analysis.two_axes import SeedStacks, bootstrap_two_axes, masked_mean
from bench.analysis.hierarchy import Units, window_weights, windows_as_units
from bench.analysis.rankings import CONFIDENCE, PRIMARY, record_units

# The report table's columns, in order (names of bench.analysis.agreement.BY_NAME).
TABLE_STATISTICS = ("tau_b", "spearman_rho", "pearson_r", "mmrv", "top1_regret")
# The statistic the verdict compares measures by (the first: an order, not a slope).
VERDICT_STATISTIC = "tau_b"


@dataclass(frozen=True)
class Rolled:
    """The rolled-out items of one backbone x suite, paired (same windows, same episodes).

    groups: item -> its seeds' records; success_by_seed: (I, S, E) per-episode success of each
    seed (an item with fewer than S seeds padded with NaN); episode_task: (E,) each episode's
    LIBERO task id."""

    items: list[str]
    groups: dict[str, list]
    success_by_seed: np.ndarray
    episode_task: np.ndarray

    @property
    def success(self) -> np.ndarray:
        """(I, E) per-episode success, mean over each item's seeds."""
        return np.nanmean(self.success_by_seed, axis=1)

    @property
    def seed_count(self) -> np.ndarray:
        return np.array([len(self.groups[i]) for i in self.items])

    @property
    def units(self) -> tuple[Units, Units]:
        """How the scored windows (held-out episodes within tasks) and the rollout episodes
        (each its own unit, within its task) are drawn: bench.analysis.hierarchy."""
        first = self.groups[self.items[0]][0]
        return record_units(first), Units(np.arange(len(self.episode_task)), self.episode_task)


@dataclass(frozen=True)
class Rows:
    """What a measure ranks: (n, W) errors and (n, E) successes, optional (n, W)/(n, E) masks."""

    labels: list[str]
    errors: np.ndarray
    success: np.ndarray
    masks: tuple[np.ndarray, np.ndarray] | None = None
    note: str = ""
    seeds: SeedStacks | None = None  # the same rows per training seed, for the bootstrap
    # The held-out windows the errors' columns are, as indices of every scored window (None:
    # all of them): what lets two measures of one window axis be drawn together (difference).
    columns: np.ndarray | None = None
    units: tuple[Units, Units] | None = None  # Rolled.units: every scored window, the episodes

    def axis_units(self) -> tuple[Units, Units] | None:
        """`units` of the errors' own columns (a subset of the scored windows: `columns`)."""
        if self.units is None or self.columns is None:
            return self.units
        windows, episodes = self.units
        return Units(windows.episode[self.columns], windows.task[self.columns]), episodes


@dataclass(frozen=True)
class OfflineMeasure:
    name: str
    definition: str
    rows: Callable[[Rolled], Rows | Undefined]


def seed_stack(per_seed: list[list]) -> np.ndarray:
    """(I, S, K) from I lists of per-seed (K,) values, an item with fewer than S seeds padded
    with NaN (never drawn: bench.analysis.two_axes.SeedStacks)."""
    width = max(len(seeds) for seeds in per_seed)
    out = np.full((len(per_seed), width, len(per_seed[0][0])), np.nan)
    for i, seeds in enumerate(per_seed):
        out[i, :len(seeds)] = seeds
    return out


def _by_seed(rolled: Rolled, per_record: Callable) -> np.ndarray | Undefined:
    """(I, S, W): each item's per-window values per seed (per_record(record) -> (W,) or
    Undefined); the first Undefined stops it."""
    out = []
    for item in rolled.items:
        values = [per_record(r) for r in rolled.groups[item]]
        bad = next((v for v in values if isinstance(v, Undefined)), None)
        if bad is not None:
            return bad
        out.append(values)
    return seed_stack(out)


def _rows(rolled: Rolled, stack: np.ndarray, note: str = "") -> Rows:
    """One row per item: its errors (mean over seeds) and success, with their per-seed stacks."""
    seeds = SeedStacks(-stack, rolled.success_by_seed, rolled.seed_count,
                       np.arange(len(rolled.items)))
    return Rows(rolled.items, np.nanmean(stack, axis=1), rolled.success, note=note, seeds=seeds,
                units=rolled.units)


def full_chunk(rolled: Rolled) -> Rows:
    """The offline score's rows: each item's per-window MSE over every real chunk step."""
    return _rows(rolled, _by_seed(rolled, lambda r: r.scores.per_window_in(PRIMARY)))


def executed_errors(record) -> list[float] | Undefined:
    """(W,) a record's per-window MSE over the chunk steps its policy executed before replanning:
    the rollout's own n_action_steps where it ran, else the one scored; per_window when that is
    the whole chunk."""
    scores = record.scores
    ran = record.run.rollout_action_steps
    n = ran if ran is not None else scores.n_action_steps
    horizon = scores.per_horizon_in(PRIMARY)
    chunk = scores.chunk_length or (len(horizon) if horizon else None)
    if n is None or chunk is None:
        return Undefined(f"{record.cell_id} keeps no n_action_steps or chunk length (a record "
                         "from before them: rescore it)")
    if n >= chunk:
        return scores.per_window_in(PRIMARY)
    if scores.per_window_executed is None or scores.n_action_steps != n:
        return Undefined(f"{record.cell_id}: the closed loop executed {n} of {chunk} steps, the "
                         "record keeps no per-window error over those steps")
    return scores.per_window_executed[PRIMARY]


def _executed(rolled: Rolled) -> Rows | Undefined:
    stack = _by_seed(rolled, executed_errors)
    if isinstance(stack, Undefined):
        return stack
    first = rolled.groups[rolled.items[0]][0]
    ran = first.run.rollout_action_steps
    n = ran if ran is not None else first.scores.n_action_steps
    horizon = first.scores.per_horizon_in(PRIMARY)
    chunk = first.scores.chunk_length or (len(horizon) if horizon else None)
    return _rows(rolled, stack, note=f"n_action_steps {n} of chunk {chunk}"
                 + (" (the full chunk)" if chunk is not None and n >= chunk else ""))


def _critical(rolled: Rolled) -> Rows | Undefined:
    records = [r for item in rolled.items for r in rolled.groups[item]]
    flags, rule = records[0].scores.window_critical, records[0].scores.critical_rule
    for r in records:
        if r.scores.window_critical is None:
            return Undefined(f"{r.cell_id} keeps no critical-window flags (a record from "
                             "before them: rescore it)")
        if (r.scores.window_critical, r.scores.critical_rule) != (flags, rule):
            return Undefined(f"{r.cell_id} flags other windows as critical (rule "
                             f"{r.scores.critical_rule} against {rule}): not paired")
    keep = np.asarray(flags, dtype=bool)
    if keep.sum() < 2:
        return Undefined(f"{int(keep.sum())} critical window(s) of {len(keep)}: nothing to average")
    stack = _by_seed(rolled, lambda r: r.scores.per_window_in(PRIMARY))[:, :, keep]
    rule_text = ", ".join(f"{k} {v}" for k, v in (rule or {}).items())
    rows = _rows(rolled, stack, note=f"{int(keep.sum())} of {len(keep)} windows ({rule_text})")
    return replace(rows, columns=np.flatnonzero(keep))


def _task_ids(record) -> dict[int, int] | Undefined:
    """{record task index: rollout task id}, matched by instruction text."""
    names = (record.run.rollouts or {}).get("task_names")
    if names is None or record.scores.window_task is None or record.scores.tasks is None:
        return Undefined(f"{record.cell_id}: its rollouts or scores do not name their tasks (a "
                         "record from before per-task rollouts)")
    by_text = {text.strip().lower(): int(t) for t, text in names.items()}
    return {i: by_text[name.strip().lower()] for i, name in enumerate(record.scores.tasks)
            if name.strip().lower() in by_text}


def _per_task(rolled: Rolled) -> Rows | Undefined:
    first = rolled.groups[rolled.items[0]][0]
    mapping = _task_ids(first)
    if isinstance(mapping, Undefined):
        return mapping
    for item in rolled.items:
        for r in rolled.groups[item]:
            if _task_ids(r) != mapping or r.scores.window_task != first.scores.window_task:
                return Undefined(f"{r.cell_id} names or places its tasks otherwise: not paired")
    full = full_chunk(rolled)
    errors, by_seed = full.errors, full.seeds
    window_task = np.asarray(first.scores.window_task)
    labels, err_rows, succ_rows, wmask, emask, item_of = [], [], [], [], [], []
    for task, task_id in sorted(mapping.items()):
        if not (window_task == task).any() or not (rolled.episode_task == task_id).any():
            continue  # a task without held-out windows or without episodes pairs nothing
        for i, item in enumerate(rolled.items):
            labels.append(f"{item} / task {task_id}")
            err_rows.append(errors[i])
            succ_rows.append(rolled.success[i])
            wmask.append(window_task == task)
            emask.append(rolled.episode_task == task_id)
            item_of.append(i)
    if not labels:
        return Undefined("no task has both held-out windows and rollout episodes")
    rows = np.array(item_of)
    seeds = SeedStacks(by_seed.predicted[rows], by_seed.actual[rows], by_seed.count[rows], rows)
    return Rows(labels, np.array(err_rows), np.array(succ_rows),
                (np.array(wmask, dtype=float), np.array(emask, dtype=float)),
                note=f"{len(labels)} item x task pairs", seeds=seeds,
                units=tuple(replace(u, by_task=True) for u in rolled.units))


MEASURES = (
    OfflineMeasure("full chunk", "MSE over every real step of each predicted chunk (the "
                   "offline score)", full_chunk),
    OfflineMeasure("executed steps", "MSE over only the first n_action_steps steps of each "
                   "chunk: what the policy executes before it replans", _executed),
    OfflineMeasure("critical interval", "MSE over the windows whose scored span lies within "
                   "+-margin frames of a gripper open/close event (bench.suites.critical)",
                   _critical),
    OfflineMeasure("per task", "each task's MSE against that task's success, ranked over "
                   "item x task pairs", _per_task),
)
assert len({m.name for m in MEASURES}) == len(MEASURES), "duplicate measure names"


@dataclass
class MeasureAgreement:
    """One measure's rows, their errors and successes, and its agreement with success."""

    name: str
    definition: str
    labels: list[str] = field(default_factory=list)
    error: list[float] = field(default_factory=list)
    success: list[float] = field(default_factory=list)
    note: str = ""
    value: dict[str, Measure] = field(default_factory=dict)
    intervals: dict[str, Interval | Undefined] = field(default_factory=dict)
    missing: str | None = None
    # VERDICT_STATISTIC of this measure minus the full chunk's, with its paired interval (both
    # measures on one draw of seeds, windows and episodes per replicate); None for the full
    # chunk itself, Undefined where the two rank other rows.
    versus_full: Measure | None = None
    versus_full_interval: Interval | Undefined | None = None
    # The same over the candidate items' rows alone (bench.analysis.candidates); None when no
    # candidate set was given.
    on_candidates: "MeasureAgreement | None" = None

    def interval_of(self, name: str) -> tuple[float, float] | None:
        ci = self.intervals.get(name)
        return (ci.low, ci.high) if isinstance(ci, Interval) else None

    def to_dict(self) -> dict:
        def plain(v):
            if isinstance(v, Undefined):
                return {"undefined": v.reason}
            return [v.low, v.high] if isinstance(v, Interval) else v

        return {"name": self.name, "definition": self.definition, "labels": self.labels,
                "offline_error": self.error, "success": self.success, "note": self.note,
                "missing": self.missing, "value": {k: plain(v) for k, v in self.value.items()},
                "intervals": {k: plain(v) for k, v in self.intervals.items()},
                f"{VERDICT_STATISTIC}_minus_full_chunk": plain(self.versus_full),
                f"{VERDICT_STATISTIC}_minus_full_chunk_interval":
                    plain(self.versus_full_interval),
                "on_candidates": self.on_candidates.to_dict() if self.on_candidates else None}


def measure_agreement(measure: OfflineMeasure, rolled: Rolled | Rows | Undefined, *,
                      n_resamples: int, seed: int = 0, confidence: float = CONFIDENCE
                      ) -> MeasureAgreement:
    """One measure's agreement with success over its rows (made from `rolled`, or given), with
    paired bootstrap intervals."""
    out = MeasureAgreement(measure.name, measure.definition)
    rows = measure.rows(rolled) if isinstance(rolled, Rolled) else rolled
    if isinstance(rows, Undefined):
        out.missing = rows.reason
        return out
    pm, am = rows.masks if rows.masks is not None else (None, None)
    error, success = masked_mean(rows.errors, pm), masked_mean(rows.success, am)
    out.labels, out.error, out.success, out.note = (rows.labels, error.tolist(),
                                                    success.tolist(), rows.note)
    out.value = {k: BY_NAME[k](-error, success) for k in TABLE_STATISTICS}
    out.intervals = bootstrap_two_axes(-rows.errors, rows.success, n_resamples=n_resamples,
                                       seed=seed, confidence=confidence,
                                       statistics=TABLE_STATISTICS, masks=rows.masks,
                                       seeds=rows.seeds, units=rows.axis_units())
    return out


def candidate_rows(rolled: Rolled, rows: Rows, candidates: frozenset[str]) -> Rows | Undefined:
    """`rows` kept where their item (rows.seeds.item, an index of rolled.items) is a candidate;
    Undefined when fewer than 2 candidate items remain."""
    keep = np.array([i for i, item in enumerate(rows.seeds.item)
                     if rolled.items[item] in candidates], dtype=int)
    items = sorted({rolled.items[rows.seeds.item[i]] for i in keep})
    if len(items) < 2:
        return Undefined(f"{len(items)} candidate item(s) rolled out: fewer than 2, nothing to "
                         "rank")
    s = rows.seeds
    return replace(rows, labels=[rows.labels[i] for i in keep], errors=rows.errors[keep],
                   success=rows.success[keep],
                   masks=None if rows.masks is None else tuple(m[keep] for m in rows.masks),
                   seeds=SeedStacks(s.predicted[keep], s.actual[keep], s.count[keep],
                                    s.item[keep]))


def measure_agreements(rolled: Rolled, candidates: frozenset[str] | None = None,
                       **kwargs) -> list[MeasureAgreement]:
    """Every registered measure's agreement with success (MEASURES' order), each after the
    first (the full chunk, the offline score) with its difference from the full chunk's; given
    `candidates` (item labels), each also over the candidate items' rows (`on_candidates`)."""
    base = MEASURES[0].rows(rolled)
    out = []
    for m in MEASURES:
        rows = base if m is MEASURES[0] else m.rows(rolled)
        agreed = measure_agreement(m, rows, **kwargs)
        if candidates is not None and not isinstance(rows, Undefined):
            agreed.on_candidates = measure_agreement(m, candidate_rows(rolled, rows, candidates),
                                                     **kwargs)
        if out and not agreed.missing and not out[0].missing:
            agreed.versus_full = _difference(out[0].value[VERDICT_STATISTIC],
                                             agreed.value[VERDICT_STATISTIC])
            if out[0].labels != agreed.labels:
                agreed.versus_full = Undefined(f"ranks {rows.note}, not the items")
            agreed.versus_full_interval = paired_difference(base, rows, **kwargs)
        out.append(agreed)
    return out


def _difference(a: Measure, b: Measure) -> Measure:
    bad = next((v for v in (a, b) if isinstance(v, Undefined)), None)
    return bad if bad is not None else b - a


def _replicate(rows: Rows, weights: np.ndarray, windows: np.ndarray, episodes: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """(predicted (n,), actual (n,)) of `rows` under one draw: seed weights (n, S), the weight
    of each scored window (W,) and each episode (E,) in the draw; None if none of the windows
    the rows read was drawn."""
    p, a = rows.seeds.apply(weights)
    w = windows if rows.columns is None else windows[rows.columns]
    if w.sum() == 0:
        return None
    return p @ w / w.sum(), a @ episodes / episodes.sum()


def paired_difference(a: Rows, b: Rows, *, n_resamples: int, seed: int = 0,
                      confidence: float = CONFIDENCE) -> Interval | Undefined:
    """Percentile interval of VERDICT_STATISTIC(b) - VERDICT_STATISTIC(a) when both measures
    rank the same items on one window axis: each replicate draws the items' seeds, the scored
    windows (held-out episodes, then windows) and the rollout episodes ONCE for both (a's
    columns are every window), so what the two share cancels. Undefined where they rank other rows (per task) or no replicate is defined."""
    if a.labels != b.labels or a.masks is not None or b.masks is not None:
        return Undefined(f"ranks {b.note or 'other rows'}, not the items")
    n_windows, n_episodes = a.errors.shape[1], a.success.shape[1]
    stat = BY_NAME[VERDICT_STATISTIC]
    rng, seed_rng = np.random.default_rng(seed), np.random.default_rng([seed, 1])
    units = a.units or (windows_as_units(n_windows), windows_as_units(n_episodes))
    # each replicate's weight on every scored window and episode (the hierarchy's draw)
    window_draws, episode_draws = (window_weights(u, n_resamples, rng) for u in units)
    diffs, reason = [], "no replicate drew a window of both"
    for k in range(n_resamples):
        weights = a.seeds.weights(seed_rng)
        windows, episodes = window_draws[k], episode_draws[k]
        drawn = [_replicate(r, weights, windows, episodes) for r in (a, b)]
        if None in drawn:
            continue
        diff = _difference(*(stat(*d) for d in drawn))
        if isinstance(diff, Undefined):
            reason = diff.reason
            continue
        diffs.append(diff)
    return percentile_intervals({"d": diffs}, {"d": reason}, n_resamples, confidence)["d"]
