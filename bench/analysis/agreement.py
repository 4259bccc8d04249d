"""Rank agreement between a cheaper tier and the one it stands in for: the one place for it.

Every function takes two score vectors over the same items, `predicted` (the cheaper tier: a
screen proxy, a short graft, another backbone's MSE) and `actual` (the tier it predicts: the full
graft, the closed loop), each (n,) float, HIGHER IS BETTER in both (pass -MSE for an MSE).

The tie rule (one rule, every statistic; quoted in the report, see TIE_RULE):
- Two scores tie when they are exactly equal (no tolerance: a tolerance would make agreement
  depend on the scale of the score).
- A tie earns no credit for an order the other side shows. Kendall tau-b counts a pair tied on
  either side as neither concordant nor discordant (tau-b's denominator corrects for ties);
  weighted tau is scipy's, which does the same with its weights; MMRV counts a pair the
  prediction ties but the actual separates as a violation (SimplerEnv's indicator
  [(S_i > S_j) != (R_i > R_j)] does exactly that); top-1 regret takes the WORST actual score
  among the items tied for the prediction's first place.
- A side on which every score ties has no order: the statistic is `Undefined` with that reason,
  never a 0 or a NaN inside a ranking. So are fewer than 2 items and non-finite scores.

Pearson r (SimplerEnv reports it beside MMRV) measures linear agreement of the two score
vectors; it is undefined on the same terms (a side without spread has no correlation).
Spearman's rho (the Critical Interval MSE study's statistic) is Pearson r of the ranks, tied
scores sharing their mean rank (SPEARMAN_TIES): under the same rule a tie orders nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Mapping, Sequence

import numpy as np
import scipy.stats

# A value or why there is none: defined below everything (bench.stats), so the stored screen
# records (bench.screen.records) hold it without importing the analysis.
from bench.stats import Measure, Undefined, as_float, is_defined  # noqa: F401  (re-exported)
from bench.analysis.hierarchy import Units, cell_weights, window_weights, windows_as_units

TIE_RULE = (
    "Scores tie when exactly equal. A tie earns no credit for an order the other side shows: "
    "Kendall tau-b counts a pair tied on either side as neither concordant nor discordant, MMRV "
    "counts a pair the cheaper tier ties but the graft separates as a violation (SimplerEnv's "
    "definition), top-1 regret takes the worst graft score among the picks tied for first. A "
    "side whose scores all tie has no order: the statistic is reported undefined, with the reason."
)
SPEARMAN_TIES = (
    "Spearman's rho is Pearson r of the ranks, tied scores sharing their mean rank, so a tie "
    "orders nothing there either."
)


def _pair(predicted: Sequence[float], actual: Sequence[float]
          ) -> tuple[np.ndarray, np.ndarray] | Undefined:
    s, r = np.asarray(predicted, dtype=float), np.asarray(actual, dtype=float)
    if s.ndim != 1 or s.shape != r.shape:
        raise ValueError(f"predicted and actual must be (n,) vectors of one length; got "
                         f"{s.shape} and {r.shape}")
    if len(s) < 2:
        return Undefined(f"{len(s)} item(s): fewer than 2, nothing to rank")
    for name, v in (("predicted", s), ("actual", r)):
        bad = np.flatnonzero(~np.isfinite(v))
        if len(bad):
            return Undefined(f"{name} score of item {int(bad[0])} is {v[bad[0]]}, not finite")
    return s, r


def _ordered(predicted, actual, sides: tuple[str, ...] = ("predicted", "actual")
             ) -> tuple[np.ndarray, np.ndarray] | Undefined:
    """The two vectors, or Undefined when a side named in `sides` ties throughout."""
    pair = _pair(predicted, actual)
    if isinstance(pair, Undefined):
        return pair
    for name, v in zip(("predicted", "actual"), pair):
        if name in sides and np.all(v == v[0]):
            return Undefined(f"every {name} score ties ({v[0]:.6g}): no order")
    return pair


def kendall_tau_b(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """Kendall tau-b of two (n,) score vectors, in [-1, 1]; undefined if a side ties throughout."""
    pair = _ordered(predicted, actual)
    if isinstance(pair, Undefined):
        return pair
    return float(scipy.stats.kendalltau(*pair, variant="b").statistic)


def kendall_p_value(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """Two-sided p of Kendall's test (scipy's method 'auto': exact when n is small and no ties)."""
    pair = _ordered(predicted, actual)
    if isinstance(pair, Undefined):
        return pair
    return float(scipy.stats.kendalltau(*pair, variant="b", method="auto").pvalue)


def weighted_tau(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """scipy's top-weighted tau (hyperbolic weigher, averaged over both rankings) of two (n,)
    higher-is-better vectors: agreement among the best items weighs most."""
    pair = _ordered(predicted, actual)
    if isinstance(pair, Undefined):
        return pair
    return float(scipy.stats.weightedtau(*pair).statistic)


def mmrv(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """SimplerEnv's mean maximum rank violation of two (n,) higher-is-better vectors, in the
    units of `actual`; 0 is perfect, lower is better.

    mean_i max_j |R_i - R_j| * [(S_i > S_j) != (R_i > R_j)], S = predicted, R = actual.
    Undefined when every actual score ties (no violation could be measured)."""
    pair = _ordered(predicted, actual, sides=("actual",))
    if isinstance(pair, Undefined):
        return pair
    s, r = pair
    violated = (s[:, None] > s[None, :]) != (r[:, None] > r[None, :])
    cost = np.abs(r[:, None] - r[None, :]) * violated
    return float(cost.max(axis=1).mean())


def top1_regret(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """Best actual score minus the actual score of the prediction's pick, >= 0, in the units of
    `actual` (for -MSE inputs: the pick's MSE minus the best MSE). Picks tied for first: the
    worst of them counts. Undefined when every predicted score ties (no pick)."""
    pair = _ordered(predicted, actual, sides=("predicted",))
    if isinstance(pair, Undefined):
        return pair
    s, r = pair
    picks = np.flatnonzero(s == s.max())
    return float(r.max() - r[picks].min())


def pearson_r(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """Pearson correlation of two (n,) higher-is-better vectors, in [-1, 1]; undefined when a
    side ties throughout (no spread to correlate)."""
    pair = _ordered(predicted, actual)
    if isinstance(pair, Undefined):
        return pair
    return float(scipy.stats.pearsonr(*pair).statistic)


def spearman_rho(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """Spearman's rank correlation of two (n,) higher-is-better vectors, in [-1, 1]; ties share
    their mean rank; undefined when a side ties throughout (no order to correlate)."""
    pair = _ordered(predicted, actual)
    if isinstance(pair, Undefined):
        return pair
    return float(scipy.stats.spearmanr(*pair).statistic)


@dataclass(frozen=True)
class Agreement:
    """The four statistics of one cheaper tier against the tier it predicts, over n items."""

    n: int
    tau_b: Measure
    weighted_tau: Measure
    mmrv: Measure
    top1_regret: Measure

    def to_dict(self) -> dict:
        """JSON-ready: numbers as floats, undefined ones as {"undefined": reason}."""
        out: dict = {"n": self.n}
        for name in ("tau_b", "weighted_tau", "mmrv", "top1_regret"):
            value = getattr(self, name)
            out[name] = {"undefined": value.reason} if isinstance(value, Undefined) else value
        return out


def agreement(predicted: Sequence[float], actual: Sequence[float]) -> Agreement:
    """All four statistics of two (n,) higher-is-better score vectors over the same items."""
    return Agreement(n=len(predicted), tau_b=kendall_tau_b(predicted, actual),
                     weighted_tau=weighted_tau(predicted, actual), mmrv=mmrv(predicted, actual),
                     top1_regret=top1_regret(predicted, actual))


STATISTICS = ("tau_b", "weighted_tau", "mmrv", "top1_regret")


@dataclass(frozen=True)
class Interval:
    """A percentile bootstrap interval of one statistic; `undefined` replicates are left out."""

    low: float
    high: float
    replicates: int
    undefined: int


# The key of a tier's tau-b minus the best naive baseline's (bootstrap_agreement's `baselines`).
NAIVE_GAP = "tau_b_minus_best_naive"


@dataclass(frozen=True)
class Draw:
    """One replicate's weights: on the (release, seed) cells (R, S) and the windows (W,)
    (bench.analysis.hierarchy: releases, seeds, held-out episodes, windows within them)."""

    cells: np.ndarray
    windows: np.ndarray


def replicate_draws(shape: tuple[int, ...], n_resamples: int, seed: int,
                    units: Units | None = None) -> Iterator[Draw]:
    """The paired bootstrap's replicates, the one place they are drawn: the hierarchical draw of
    per-window scores of `shape` (n, W) or (n, R, S, W), once for every item and every tier
    scored on them (so two tiers' statistics of one replicate are paired). `units` groups the W
    windows into held-out episodes (None: each window its own unit)."""
    n_rel, n_seed = shape[1:3] if len(shape) == 4 else (1, 1)
    units = units if units is not None else windows_as_units(shape[-1])
    rng = np.random.default_rng(seed)
    windows = window_weights(units, n_resamples, rng)
    cells = cell_weights(n_rel, n_seed, n_resamples, rng)
    for b in range(n_resamples):
        yield Draw(cells[b], windows[b])


def pairwise_tau_b(predicted: Sequence[float], actual: Sequence[float]) -> Measure:
    """kendall_tau_b by counting the n(n-1)/2 pairs in numpy: the same statistic (to rounding)
    and the same undefined cases, without scipy's per-call cost, for the few items a bootstrap
    ranks thousands of times."""
    pair = _ordered(predicted, actual)
    if isinstance(pair, Undefined):
        return pair
    upper = np.triu_indices(len(pair[0]), 1)
    sx, sy = (np.sign(v[:, None] - v[None, :])[upper] for v in pair)
    return float((sx * sy).sum() / np.sqrt(np.count_nonzero(sx) * np.count_nonzero(sy)))


def naive_gap(predicted: np.ndarray, actual: np.ndarray,
              baselines: Mapping[str, np.ndarray]) -> Measure:
    """Kendall tau-b of `predicted` (n,) with `actual` (n,) minus the largest tau-b of any
    baseline's (n,) scores (the best naive baseline on these items, higher is better); undefined
    when the tier's tau-b is, or every baseline's is. Both sides counted alike
    (pairwise_tau_b), so a baseline equal to the tier differs from it by exactly 0."""
    own = pairwise_tau_b(predicted, actual)
    if isinstance(own, Undefined):
        return own
    taus = {name: pairwise_tau_b(b, actual) for name, b in baselines.items()}
    defined = [t for t in taus.values() if not isinstance(t, Undefined)]
    if not defined:
        return Undefined("no naive baseline orders these items: "
                         + "; ".join(f"{n} {t}" for n, t in taus.items()) if taus else
                         "no naive baseline scores these items")
    return own - max(defined)


def _mean_over(scores: np.ndarray, draw: Draw) -> np.ndarray:
    """(n,) scores as drawn: fixed (n,) ones as they are, (n, W) ones averaged over the drawn
    windows, (n, R, S, W) ones over the drawn windows, then the drawn cells (absent: NaN)."""
    if scores.ndim == 1:
        return scores
    if scores.ndim == 2:
        return scores @ draw.windows
    per_cell = np.nan_to_num(scores) @ draw.windows  # (n, R, S)
    weights = np.isfinite(scores[..., 0]) * draw.cells
    with np.errstate(invalid="ignore", divide="ignore"):
        return (per_cell * weights).sum(axis=(1, 2)) / weights.sum(axis=(1, 2))


def bootstrap_agreement(predicted: np.ndarray, actual: np.ndarray, n_resamples: int = 1000,
                        seed: int = 0, confidence: float = 0.95,
                        baselines: Mapping[str, np.ndarray] | None = None,
                        units: Units | None = None) -> dict[str, Interval | Undefined]:
    """Paired hierarchical bootstrap of the four statistics: each replicate draws releases,
    seeds, held-out episodes (`units`) and windows ONCE for all n items (replicate_draws) and
    re-averages both tiers over them.

    predicted: (n,) fixed scores, per-window scores of `actual`'s shape, or (n, W) on its
    windows with cells of its own held (only the windows drawn); actual: (n, W) or
    (n, R, S, W) per-window scores (higher is better: -MSE; NaN rows for absent cells).
    baselines: {name: (n,) scores} of the naive baselines on the same items: the result also
    holds NAIVE_GAP, the interval of naive_gap on the same replicates (the tier and the
    baselines against one draw of the graft). Percentile interval over the replicates where a
    statistic is defined; Undefined when none is."""
    actual = np.asarray(actual, dtype=float)
    predicted = np.asarray(predicted, dtype=float)
    if actual.ndim not in (2, 4) or predicted.shape not in ((len(actual),), actual.shape,
                                                            (len(actual), actual.shape[-1])):
        raise ValueError(f"actual must be (n, W) or (n, R, S, W) and predicted (n,), (n, W) or "
                         f"of actual's shape; got {actual.shape} and {predicted.shape}")
    base = {k: np.asarray(v, dtype=float) for k, v in (baselines or {}).items()}
    values: dict[str, list[float]] = {k: [] for k in STATISTICS}
    if baselines is not None:
        values[NAIVE_GAP] = []
    reasons: dict[str, str] = {}
    for w in replicate_draws(actual.shape, n_resamples, seed, units):
        s, r = _mean_over(predicted, w), _mean_over(actual, w)
        a = agreement(s, r)
        replicate = {k: getattr(a, k) for k in STATISTICS}
        if baselines is not None:
            replicate[NAIVE_GAP] = naive_gap(s, r, {k: _mean_over(v, w) for k, v in base.items()})
        keep_replicate(values, reasons, replicate)
    return percentile_intervals(values, reasons, n_resamples, confidence)


def keep_replicate(values: dict[str, list[float]], reasons: dict[str, str],
          replicate: dict[str, Measure]) -> None:
    """One bootstrap replicate's statistics: a defined value kept, an undefined one's reason."""
    for k, v in replicate.items():
        if isinstance(v, Undefined):
            reasons.setdefault(k, v.reason)
        else:
            values[k].append(v)


def percentile_intervals(values: dict[str, list[float]], reasons: dict[str, str],
                         n_resamples: int, confidence: float
                         ) -> dict[str, Interval | Undefined]:
    """Percentile interval per statistic over its defined replicates; Undefined when none is."""
    alpha = (1 - confidence) / 2
    out: dict[str, Interval | Undefined] = {}
    for k, v in values.items():
        if not v:
            out[k] = Undefined(f"every replicate undefined: {reasons.get(k)}")
            continue
        out[k] = Interval(float(np.quantile(v, alpha)), float(np.quantile(v, 1 - alpha)),
                          len(v), n_resamples - len(v))
    return out


WITH_PEARSON = (*STATISTICS, "pearson_r")
# Every statistic by name, for a caller that picks a few (bench.analysis.offline_measures).
BY_NAME = {"tau_b": kendall_tau_b, "weighted_tau": weighted_tau, "mmrv": mmrv,
           "top1_regret": top1_regret, "pearson_r": pearson_r, "spearman_rho": spearman_rho}
