"""Agreement when the two tiers are measured on different units: offline scores over held-out
windows against closed-loop success over rollout episodes (bench.analysis.rollouts,
offline_measures, robust_loop), each replicate drawing both axes (and each item's seeds) once for
all items; the statistics and the percentile rule are bench.analysis.agreement's."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.analysis.agreement import (BY_NAME, WITH_PEARSON, Interval, Undefined, keep_replicate,
                                      percentile_intervals)
from bench.analysis.hierarchy import window_weights


def masked_mean(scores: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """(n,) row means of (n, K) `scores` over the columns `mask` (n, K) keeps (None: all); NaN
    where a row keeps none (its statistics are then undefined, never 0)."""
    if mask is None:
        return scores.mean(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (scores * mask).sum(axis=1) / mask.sum(axis=1)


@dataclass(frozen=True)
class SeedStacks:
    """Each row's scores per training seed, for a bootstrap that draws seeds too: predicted
    (n, S, W) and actual (n, S, E), a row with fewer than S seeds padded (its pads never drawn);
    count (n,) the seeds of each row; item (n,) the item a row belongs to (an item's rows, e.g.
    its item x task pairs, share one draw of its seeds)."""

    predicted: np.ndarray
    actual: np.ndarray
    count: np.ndarray
    item: np.ndarray

    def weights(self, rng: np.random.Generator) -> np.ndarray:
        """(n, S): each item's seeds drawn with replacement (as many as it has), as each row's
        weight on its seeds (a seed drawn twice weighs 2 / count)."""
        weights = np.zeros(self.predicted.shape[:2])
        for item in np.unique(self.item):
            rows = np.flatnonzero(self.item == item)
            n = int(self.count[rows[0]])
            weights[rows] = np.bincount(rng.integers(0, n, n), minlength=weights.shape[1]) / n
        return weights

    def apply(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, W) and (n, E): each row averaged over its seeds with `weights` (n, S)."""
        return (np.einsum("ns,nsw->nw", weights, np.nan_to_num(self.predicted)),
                np.einsum("ns,nse->ne", weights, np.nan_to_num(self.actual)))

    def draw(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(n, W) and (n, E) of one draw of the seeds (`weights`). One seed: that seed's
        scores, bit for bit."""
        return self.apply(self.weights(rng))


def bootstrap_two_axes(predicted: np.ndarray, actual: np.ndarray, n_resamples: int = 1000,
                       seed: int = 0, confidence: float = 0.95, *,
                       statistics: tuple[str, ...] = WITH_PEARSON,
                       masks: tuple[np.ndarray, np.ndarray] | None = None,
                       seeds: SeedStacks | None = None,
                       units: tuple | None = None) -> dict[str, Interval | Undefined]:
    """Paired bootstrap when the two tiers are measured on different units: each replicate draws
    the W columns of `predicted` and, independently, the E columns of `actual` with replacement,
    ONCE for all n items, and re-averages both (e.g. offline -MSE over held-out windows against
    closed-loop success over rollout episodes that every item shares).

    predicted: (n, W) per-window scores; actual: (n, E) per-episode scores; both higher is
    better. Intervals of `statistics` (names of BY_NAME; default the four and Pearson r).
    masks: (n, W) and (n, E) 0/1 weights, row i averaging only the columns its masks keep (an
    item x task pair: its task's windows and episodes); the draws are the same either way.
    seeds: the same scores per training seed (SeedStacks): each replicate first draws every
    item's seeds (its own random stream, so items of one seed each give the two-axis intervals
    exactly), then the windows and episodes of that draw: the training's variance enters.
    units: (Units of the W columns, Units of the E columns) (bench.analysis.hierarchy): each
    axis drawn as the rankings draw it, episodes (within tasks) then windows within a drawn
    episode, n - 1 of n at each level, instead of its columns one by one; a rollout episode is
    its own unit of one column, drawn within its task."""
    predicted = np.asarray(predicted, dtype=float)
    actual = np.asarray(actual, dtype=float)
    if predicted.ndim != 2 or actual.ndim != 2 or len(predicted) != len(actual):
        raise ValueError(f"predicted must be (n, W) and actual (n, E); got {predicted.shape} and "
                         f"{actual.shape}")
    pm, am = (None, None) if masks is None else (np.asarray(m, dtype=float) for m in masks)
    rng, seed_rng = np.random.default_rng(seed), np.random.default_rng([seed, 1])
    if units is not None:  # (B, W) and (B, E) weights of each replicate's hierarchical draw
        column_weights = [window_weights(u, n_resamples, rng) for u in units]
    values: dict[str, list[float]] = {k: [] for k in statistics}
    reasons: dict[str, str] = {}
    for b in range(n_resamples):
        p, a = (predicted, actual) if seeds is None else seeds.draw(seed_rng)
        if units is not None:
            wp, wa = (weights[b][None, :] for weights in column_weights)
            s = masked_mean(p, wp if pm is None else pm * wp)
            r = masked_mean(a, wa if am is None else am * wa)
        else:
            w = rng.integers(0, predicted.shape[1], predicted.shape[1])
            e = rng.integers(0, actual.shape[1], actual.shape[1])
            s = masked_mean(p[:, w], None if pm is None else pm[:, w])
            r = masked_mean(a[:, e], None if am is None else am[:, e])
        keep_replicate(values, reasons, {k: BY_NAME[k](s, r) for k in statistics})
    return percentile_intervals(values, reasons, n_resamples, confidence)
