"""The verdict within the working group: the closed-loop order of the candidates that work, with
intervals, and how far offline MSE agrees with it there.

Telling working encoders from failing ones is the easy half of the closed-loop question; a team
asks which of its plausible encoders succeeds most. Per backbone x suite, over the rolled-out
items (record labels, each over its releases and seeds: bench.analysis.rollouts' items):

- **working** (WORKING_RULE): a candidate (bench.analysis.candidates) whose success is measured
  above the failing reference's: its paired difference with the reference, on the episodes both
  ran, has an interval above 0. The reference is the best-succeeding rolled-out graft of an
  encoder without trained weights (a random twin, a known-answer encoder such as blind or
  pixels): what the policy reaches without trained vision. Without one the reference is success
  0 (the item's own interval must lie above 0).
- the working items in closed-loop order (success, highest first), each neighbour pair's paired
  difference with its interval (resolved: the interval excludes 0);
- Kendall tau-b of -MSE and success among the working items, with its interval, and how many of
  the resolved neighbour pairs offline MSE orders the same way;
- for each open pair, how many more paired episodes it needs (OPEN_PAIR_RULE: Connor's sample
  size for McNemar's test at the observed discordance).

Intervals: one hierarchical draw per replicate for every item (bench.analysis.hierarchy):
releases, seeds within a release, rollout episodes within their task (an episode is a task and
init state, with the same env seed for every item, so items are paired on it) and, for offline
MSE, held-out episodes and windows; a cell's success and MSE share its release and seed draw.
Items rolled out on different episodes (a sequential study runs some items more rounds) are each
averaged over their own; a neighbour difference over the episodes both ran. Percentile
intervals: a sequential study looks at its data between rounds, so they describe, and the
design's anytime-valid declarations (bench.analysis.sequential) decide.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np
from scipy.stats import norm

from bench.analysis.agreement import Interval, Undefined, pairwise_tau_b, percentile_intervals
from bench.analysis.hierarchy import Units, cell_weights, percentile, window_weights
from bench.analysis.rankings import CONFIDENCE, WindowMismatchError, cell_arrays
from bench.analysis.rollouts import rolled_out
from bench.grid.kinds import GRAFT, record_label
from bench.results.record import NORMALIZED

WORKING_RULE = (
    "A candidate works when its success is measured above the failing reference's: its paired "
    "difference with the reference, on the episodes both ran, has a 95% interval above 0. The "
    "reference is the best-succeeding rolled-out graft of an encoder without trained weights (a "
    "random twin, a known-answer encoder such as blind or pixels: what the policy reaches "
    "without trained vision); without one, success 0.")
POWER = 0.8
OPEN_PAIR_RULE = (
    "Paired episodes an open pair needs (Connor 1987, McNemar's paired test, two-sided alpha "
    f"{1 - CONFIDENCE:.2f}, power {POWER:.0%}): n = (z_a sqrt(p_d) + z_b sqrt(p_d - d^2))^2 / "
    "d^2, with p_d the share of paired episodes where exactly one of the two succeeded and d "
    "the upper item's share minus the lower's (each item's outcome on an episode the mean over "
    "its cells); 'more' is n minus the paired episodes run. A paired episode is a task and init "
    "state that every cell of both items ran (with 3 releases, 3 rollouts of each item). d = 0: "
    "no size resolves it. A pair open at or past n is held open by the seeds or releases, not by "
    "the episodes.")


def mcnemar_episodes(upper_only: float, lower_only: float, *, confidence: float = CONFIDENCE,
                     power: float = POWER) -> float:
    """Paired episodes McNemar's test needs to resolve a pair whose shares of episodes where
    only the upper / only the lower item succeeded are these (Connor 1987); inf when equal."""
    discordant, d = upper_only + lower_only, upper_only - lower_only
    # Shares averaged over cells (1/3, 2/3 of an episode) differ in their last bits when equal.
    if abs(d) < 1e-9:
        return math.inf
    z_a, z_b = norm.ppf(1 - (1 - confidence) / 2), norm.ppf(power)
    return (z_a * math.sqrt(discordant) + z_b * math.sqrt(discordant - d * d)) ** 2 / d ** 2


@dataclass
class ItemSuccess:
    """One rolled-out item: success over its cells (releases x seeds) and episodes."""

    item: str
    candidate: bool
    working: bool
    cells: int
    episodes: int  # episode outcomes (cells x episodes each)
    success: float
    ci: tuple[float, float]
    mse: float


@dataclass
class NeighbourPair:
    """Two neighbours of the closed-loop order, paired on the episodes both ran."""

    upper: str
    lower: str
    paired_episodes: int
    upper_only: float  # share of paired episodes where only the upper item succeeded
    lower_only: float
    diff: float  # success of upper minus lower, on the paired episodes
    ci: tuple[float, float]
    resolved: bool
    mse_agrees: bool  # offline MSE is lower for the upper item
    needed: float | None = None  # paired episodes McNemar needs (open pairs)
    more: float | None = None  # needed minus those run (>= 0; inf: no size resolves it)


@dataclass
class WorkingGroup:
    """The verdict within the working group of one backbone x suite."""

    backbone: str
    suite: str
    items: list[ItemSuccess] = field(default_factory=list)  # every rolled-out item, by success
    reference: str | None = None  # the failing reference (None: success 0)
    order: list[str] = field(default_factory=list)  # the working items, best first
    pairs: list[NeighbourPair] = field(default_factory=list)
    tau_b: float | Undefined = Undefined("no working group")
    tau_b_ci: Interval | Undefined = Undefined("no working group")
    n_resamples: int = 0
    missing: str | None = None

    @property
    def open_pairs(self) -> list[NeighbourPair]:
        return [p for p in self.pairs if not p.resolved]

    def to_dict(self) -> dict:
        out = asdict(self)
        for key in ("tau_b", "tau_b_ci"):
            value = getattr(self, key)
            out[key] = {"undefined": value.reason} if isinstance(value, Undefined) else \
                (asdict(value) if isinstance(value, Interval) else value)
        return out


@dataclass(frozen=True)
class Outcomes:
    """Success per episode of every item: values (I, R, S, K) 0/1, NaN where a (release, seed)
    cell did not run episode k; keys (K,) (task, episode) and their units (episodes in tasks)."""

    items: list[str]
    values: np.ndarray
    keys: list[tuple[int, int]]
    units: Units

    def ran(self) -> np.ndarray:
        """(I, K) bool: the item ran episode k in at least one of its cells."""
        return np.isfinite(self.values).any(axis=(1, 2))

    def per_episode(self, i: int) -> np.ndarray:
        """(K,) item i's mean outcome per episode over the cells that ran it (NaN: none)."""
        rows = self.values[i].reshape(-1, len(self.keys))
        ran = np.isfinite(rows).any(axis=0)
        out = np.full(len(self.keys), np.nan)
        out[ran] = np.nanmean(rows[:, ran], axis=0)
        return out


def outcomes(groups: dict[str, list], items: list[str], releases: list[int],
             seeds: list[int]) -> Outcomes | str:
    """The items' episodes as Outcomes, or why they are not paired (an episode key whose init
    state differs between records)."""
    init: dict[tuple[int, int], int] = {}
    for records in groups.values():
        for r in records:
            for e in r.run.rollouts["episodes"]:
                key = (int(e["task"]), int(e["episode"]))
                state = int(e.get("init_state", -1))
                if init.setdefault(key, state) != state:
                    return (f"{r.cell_id} rolled out task {key[0]} episode {key[1]} from init "
                            f"state {state}, another record from {init[key]}: not paired")
    keys = sorted(init)
    at = {k: n for n, k in enumerate(keys)}
    values = np.full((len(items), len(releases), len(seeds), len(keys)), np.nan)
    for i, item in enumerate(items):
        for r in groups[item]:
            cell = values[i, releases.index(int(r.release)), seeds.index(int(r.seed))]
            for e in r.run.rollouts["episodes"]:
                cell[at[(int(e["task"]), int(e["episode"]))]] = float(bool(e["success"]))
    ids = np.arange(len(keys))
    return Outcomes(items, values, keys, Units(ids, np.array([k[0] for k in keys])))


def weighted_means(values: np.ndarray, keep: np.ndarray, unit_w: np.ndarray,
                   cell_w: np.ndarray) -> np.ndarray:
    """(I, B) each row's mean under B draws: values (I, R, S, K) NaN where absent, keep (I, K)
    the columns a row averages, unit_w (B, K) the draw's weight on each column, cell_w (B, R, S)
    on each cell. A cell averages its present kept columns; a row its cells with any (NaN where
    none was drawn)."""
    present = np.isfinite(values) & keep[:, None, None, :]
    filled = np.where(present, values, 0.0)
    num = np.einsum("irsk,bk->irsb", filled, unit_w)
    den = np.einsum("irsk,bk->irsb", present.astype(float), unit_w)
    with np.errstate(invalid="ignore", divide="ignore"):
        cell = num / den
    weight = np.moveaxis(cell_w, 0, -1)[None] * np.isfinite(cell)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (np.nan_to_num(cell) * weight).sum(axis=(1, 2)) / weight.sum(axis=(1, 2))


@dataclass(frozen=True)
class Draws:
    """The point estimate (column 0) and B replicates (columns 1..B) of one hierarchical draw:
    weights on rollout episodes (B+1, K), offline windows (B+1, W) and cells (B+1, R, S)."""

    episodes: np.ndarray
    windows: np.ndarray
    cells: np.ndarray

    @classmethod
    def of(cls, episode_units: Units, window_units: Units, shape: tuple[int, int],
           n_resamples: int, seed: int) -> Draws:
        rng = np.random.default_rng(seed)
        ew = window_weights(episode_units, n_resamples, rng)
        ww = window_weights(window_units, n_resamples, rng)
        cw = cell_weights(*shape, n_resamples, rng)
        uniform = lambda n: np.full((1, n), 1.0 / n)  # noqa: E731
        return cls(np.vstack([uniform(ew.shape[1]), ew]), np.vstack([uniform(ww.shape[1]), ww]),
                   np.concatenate([np.ones((1, *shape)), cw]))


def pair_difference(out: Outcomes, i: int, j: int, draws: Draws) -> tuple[np.ndarray, int]:
    """((B+1,) success of i minus j on the episodes both ran, point first; their count)."""
    both = out.ran()[i] & out.ran()[j]
    means = weighted_means(out.values[[i, j]], np.stack([both, both]), draws.episodes,
                           draws.cells)
    return means[0] - means[1], int(both.sum())


def _interval(draws: np.ndarray) -> tuple[float, float]:
    lo, hi = percentile(draws[None, 1:], CONFIDENCE)
    return float(lo[0]), float(hi[0])


def working_items(out: Outcomes, candidates: frozenset[str], reference: int | None,
                  success: np.ndarray, draws: Draws) -> list[bool]:
    """WORKING_RULE for every item (a non-candidate never works here)."""
    flags = []
    for i, item in enumerate(out.items):
        if item not in candidates:
            flags.append(False)
            continue
        if reference is None:
            flags.append(_interval(success[i])[0] > 0)
            continue
        diff, n = pair_difference(out, i, reference, draws)
        flags.append(n > 0 and _interval(diff)[0] > 0)
    return flags


def neighbour(out: Outcomes, i: int, j: int, mse: np.ndarray, draws: Draws) -> NeighbourPair:
    """The pair (upper i, lower j) of the closed-loop order, with McNemar's size when open."""
    diff, n = pair_difference(out, i, j, draws)
    ci = _interval(diff)
    both = out.ran()[i] & out.ran()[j]
    a, b = out.per_episode(i)[both], out.per_episode(j)[both]
    upper_only = float(np.mean(a * (1 - b))) if n else 0.0
    lower_only = float(np.mean((1 - a) * b)) if n else 0.0
    pair = NeighbourPair(out.items[i], out.items[j], n, upper_only, lower_only, float(diff[0]),
                         ci, resolved=bool(ci[0] > 0 or ci[1] < 0),
                         mse_agrees=bool(mse[i] < mse[j]))
    if not pair.resolved:
        pair.needed = mcnemar_episodes(upper_only, lower_only)
        pair.more = max(math.ceil(pair.needed) - n, 0) if math.isfinite(pair.needed) \
            else math.inf
    return pair


def working_group(records: Sequence, backbone: str, suite: str, candidates: frozenset[str], *,
                  n_resamples: int = 1000, random_seed: int = 0) -> WorkingGroup:
    """The verdict within the working group of `backbone` x `suite` (module docstring)."""
    wg = WorkingGroup(backbone, suite, n_resamples=n_resamples)
    rolled = [r for r in records if r.backbone == backbone and r.suite == suite
              and rolled_out(r)]
    try:
        ca = cell_arrays(rolled, record_label, (NORMALIZED,)) if rolled else None
    except WindowMismatchError as err:
        wg.missing = str(err)
        return wg
    if ca is None:
        wg.missing = "no rolled-out item"
        return wg
    groups: dict[str, list] = {}
    for r in rolled:
        groups.setdefault(record_label(r), []).append(r)
    out = outcomes(groups, ca.items, ca.releases, ca.seeds)
    if isinstance(out, str):
        wg.missing = out
        return wg
    draws = Draws.of(out.units, ca.units, (len(ca.releases), len(ca.seeds)), n_resamples,
                     random_seed)
    offline = ca.values[NORMALIZED]
    success = weighted_means(out.values, out.ran(), draws.episodes, draws.cells)  # (I, B+1)
    mse = weighted_means(offline, np.ones((len(out.items), offline.shape[-1]), bool),
                         draws.windows, draws.cells)
    reference = _reference(groups, out.items, candidates, success[:, 0])
    wg.reference = None if reference is None else out.items[reference]
    flags = working_items(out, candidates, reference, success, draws)
    for i, item in enumerate(out.items):
        wg.items.append(ItemSuccess(
            item, item in candidates, flags[i], len(groups[item]),
            int(np.isfinite(out.values[i]).sum()), float(success[i, 0]),
            _interval(success[i]), float(mse[i, 0])))
    wg.items.sort(key=lambda s: (-s.success, s.item))
    working = [out.items.index(s.item) for s in wg.items if s.working]
    wg.order = [out.items[i] for i in working]
    wg.pairs = [neighbour(out, i, j, mse[:, 0], draws) for i, j in zip(working, working[1:])]
    if len(working) >= 2:
        wg.tau_b, wg.tau_b_ci = _tau_b(mse[working], success[working], n_resamples)
    else:
        wg.tau_b = wg.tau_b_ci = Undefined(f"{len(working)} working item(s): fewer than 2")
    return wg


def _reference(groups: dict[str, list], items: list[str], candidates: frozenset[str],
               success: np.ndarray) -> int | None:
    """The best-succeeding non-candidate graft item (WORKING_RULE's reference), or None."""
    failing = [i for i, item in enumerate(items)
               if item not in candidates and groups[item][0].kind == GRAFT]
    return max(failing, key=lambda i: (success[i], items[i]), default=None)


def _tau_b(mse: np.ndarray, success: np.ndarray, n_resamples: int):
    """Kendall tau-b of -MSE and success (rows: items; column 0 the point) and its interval."""
    values: dict[str, list[float]] = {"tau_b": []}
    reasons: dict[str, str] = {}
    for b in range(1, mse.shape[1]):
        tau = pairwise_tau_b(-mse[:, b], success[:, b])
        if isinstance(tau, Undefined):
            reasons.setdefault("tau_b", tau.reason)
        elif math.isfinite(tau):
            values["tau_b"].append(tau)
    ci = percentile_intervals(values, reasons, n_resamples, CONFIDENCE)["tau_b"]
    return pairwise_tau_b(-mse[:, 0], success[:, 0]), ci


def working_groups(records: Sequence, candidates: frozenset[str], **kwargs) -> list[WorkingGroup]:
    """One WorkingGroup per backbone x suite with rolled-out candidates."""
    pairs = sorted({(r.backbone, r.suite) for r in records if rolled_out(r)
                    and record_label(r) in candidates})
    return [working_group(records, b, s, candidates, **kwargs) for b, s in pairs]
