"""The variance budget of encoder differences: how much of a paired difference's uncertainty
comes from releases, seeds, held-out episodes, and what it would take to resolve the leading pair.

For one backbone x suite and one encoder against the leader, the paired per-episode differences
D[r, s, k] (release r, seed s within it, held-out episode k; every cell scores every episode)
follow D = mu + a_r + b_s(r) + c_k + e_rsk, with independent zero-mean effects of variances
s2_release, s2_seed, s2_episode, s2_residual (bench.analysis.hierarchy.components: method of
moments, negative estimates set to 0). The mean difference over R releases x S seeds x K
episodes then has variance

    V(R, S, K) = s2_release / R + s2_seed / (R S) + s2_episode / K + s2_residual / (R S K)

and a normal 95% interval excludes 0 at the observed gap g when 1.96 sqrt(V) < |g|. The moments
give the split; the total is the report's own interval's (`calibrated`), so the measured counts
resolve the pair exactly when the ranking's interval excludes 0. "What it would take" solves
that for one count at a time, the others kept as measured, and for all three scaled alike.
Assumptions: the
components are the same at other counts, the gap is the true one (a smaller true gap needs more),
effects are independent and roughly normal, and one recipe is measured (a different native
recipe is another population of releases).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from bench.analysis.hierarchy import Components, components, episode_means, t_expansion
from bench.analysis.rankings import (PRIMARY, Ranking, WindowMismatchError, cell_arrays,
                                     graft_records)

Z = 1.959963984540054  # the normal 97.5% quantile
MAX_COUNT = 10_000  # counts past this are reported as "not by this level alone"


@dataclass
class PairBudget:
    """One encoder's difference against the leader: gap (encoder - leader, normalised MSE),
    the components and shares at the measured counts."""

    encoder: str
    gap: float
    parts: Components
    shares: dict[str, float]


@dataclass
class Budget:
    """A backbone x suite's budget: each encoder's pair against the leader, and for the leading
    pair (leader vs runner-up) the smallest counts that would resolve it, one level at a time."""

    backbone: str
    suite: str
    leader: str
    counts: tuple[int, int, int]  # releases, seeds, episodes measured
    pairs: list[PairBudget] = field(default_factory=list)
    needed: dict[str, int | None] = field(default_factory=dict)  # level -> count (None: no)
    all_levels: float | None = None  # the factor on every count that resolves it (None: > 100)
    error: str | None = None

    def to_dict(self) -> dict:
        return {"backbone": self.backbone, "suite": self.suite, "leader": self.leader,
                "counts": dict(zip(("releases", "seeds", "episodes"), self.counts)),
                "pairs": [{"encoder": p.encoder, "gap": p.gap, "shares": p.shares,
                           "components": {"release": p.parts.release, "seed": p.parts.seed,
                                          "episode": p.parts.episode,
                                          "residual": p.parts.residual},
                           "df": p.parts.df} for p in self.pairs],
                "needed": self.needed, "all_levels_factor": self.all_levels,
                "error": self.error}


def resolves(parts: Components, gap: float, releases: int, seeds: int, episodes: int) -> bool:
    """Whether a normal 95% interval of the mean difference at these counts excludes 0."""
    return Z * np.sqrt(parts.mean_variance(releases, seeds, episodes)) < abs(gap)


def smallest_count(parts: Components, gap: float, level: str) -> int | None:
    """The smallest count of `level` ('releases', 'seeds', 'episodes') that resolves `gap`, the
    other two as measured; None when no count up to MAX_COUNT does (the others' share alone is
    too large)."""
    measured = dict(zip(("releases", "seeds", "episodes"), parts.shape))
    if resolves(parts, gap, **measured):
        return measured[level]
    n = measured[level]
    while n <= MAX_COUNT:  # V falls monotonically in each count: double, then bisect
        if resolves(parts, gap, **{**measured, level: n}):
            break
        n *= 2
    else:
        return None
    lo = max(n // 2, measured[level])
    while lo < n:
        mid = (lo + n) // 2
        if resolves(parts, gap, **{**measured, level: mid}):
            n = mid
        else:
            lo = mid + 1
    return n


def calibrated(parts: Components, interval: tuple[float, float]) -> Components:
    """`parts` scaled so that their variance at the measured counts is the one the report's
    interval shows (half-width / (1.96 t/z)): the moments' split, the bootstrap's total, so
    "resolved at the measured counts" means what the ranking's interval says."""
    lo, hi = interval
    own = parts.mean_variance()
    if not (np.isfinite(lo) and np.isfinite(hi)) or own <= 0 or hi <= lo:
        return parts
    half = (hi - lo) / 2 / t_expansion(parts.df)
    scale = (half / Z) ** 2 / own
    return replace(parts, release=parts.release * scale, seed=parts.seed * scale,
                   episode=parts.episode * scale, residual=parts.residual * scale)


def scale_factor(parts: Components, gap: float) -> float | None:
    """The smallest factor f (to 0.1) by which multiplying releases, seeds and episodes alike
    resolves `gap`; None past 100."""
    r, s, k = parts.shape
    f = 1.0
    while f <= 100:
        if resolves(parts, gap, int(np.ceil(r * f)), int(np.ceil(s * f)), int(np.ceil(k * f))):
            return f
        f = round(f + 0.1, 1) if f < 4 else f * 1.25
    return None


def variance_budget(records: Sequence, ranking: Ranking) -> Budget:
    """The budget of `ranking`'s backbone x suite from its graft records (complete tables only:
    an encoder missing a release or seed is left out of the pairs, said in `error`)."""
    budget = Budget(ranking.backbone, ranking.suite, ranking.leader or "", (0, 0, 0))
    cells = graft_records(records, ranking.backbone, ranking.suite)
    if not cells or ranking.leader is None:
        budget.error = "no ranking"
        return budget
    try:
        ca = cell_arrays(cells, lambda c: c.encoder, (PRIMARY,))
    except WindowMismatchError as e:
        budget.error = str(e)
        return budget
    tables = episode_means(ca.values[PRIMARY], ca.units)  # (E, R, S, K)
    budget.counts = tables.shape[1:]
    lead = tables[ca.items.index(ranking.leader)]
    skipped = []
    for result in ranking.encoders[1:]:
        table = tables[ca.items.index(result.encoder)] - lead
        if not np.all(np.isfinite(table)):
            skipped.append(result.encoder)
            continue
        parts = calibrated(components(table), result.diff_ci[PRIMARY])
        # the gap as the ranking reads it (windows weighted, not episodes): one figure per pair
        gap = float(result.diff[PRIMARY])
        budget.pairs.append(PairBudget(result.encoder, gap, parts, parts.shares()))
    if skipped:
        budget.error = (f"left out (a release or seed missing on it or the leader): "
                        f"{', '.join(skipped)}")
    if budget.pairs:
        first = budget.pairs[0]
        budget.needed = {level: smallest_count(first.parts, first.gap, level)
                         for level in ("releases", "seeds", "episodes")}
        budget.all_levels = scale_factor(first.parts, first.gap)
    return budget
