"""The paired interval of two cells scored on the same held-out windows (the regression
baseline's noise rule, docs/CI.md): their per-window differences aligned by window id, the mean,
and the report's paired bootstrap drawing held-out episodes, then windows."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from bench.results.record import Record

CONFIDENCE = 0.95
N_RESAMPLES = 2000


def paired_interval(now: Sequence[float], base: Sequence[float], units=None, *,
                    confidence: float = CONFIDENCE, n_resamples: int = N_RESAMPLES,
                    seed: int = 0) -> tuple[float, float, float]:
    """(mean, lo, hi) of the per-window differences now - base, (W,) each, paired by position:
    the report's paired bootstrap (bench.analysis.rankings) on the two cells, drawing the
    held-out episodes of `units` (bench.analysis.hierarchy.Units; None: each window its own),
    then their windows; lo = hi = NaN with fewer than 2 windows."""
    from bench.analysis.hierarchy import windows_as_units
    from bench.analysis.rankings import paired_bootstrap

    rows = np.stack([np.asarray(base, dtype=float), np.asarray(now, dtype=float)])
    if rows.shape[-1] == 0:
        return math.nan, math.nan, math.nan
    units = units if units is not None else windows_as_units(rows.shape[-1])
    boot = paired_bootstrap(rows[:, None, None, :], units, 0, n_resamples=n_resamples,
                            confidence_level=confidence, random_seed=seed)
    return float(boot.diff[1]), float(boot.diff_lo[1]), float(boot.diff_hi[1])


def aligned(a: Record, b: Record, space: str) -> tuple[np.ndarray, np.ndarray, object]:
    """Per-window MSE of cells a and b in `space`, restricted to their common window ids, and
    the held-out episodes of those windows (a's ids, else b's; windows alone when neither
    record carries them)."""
    from bench.analysis.rankings import record_units

    index_b = {w: i for i, w in enumerate(b.scores.window_ids)}
    pairs = [(i, index_b[w]) for i, w in enumerate(a.scores.window_ids) if w in index_b]
    pa = np.asarray(a.scores.per_window_in(space), dtype=float)
    pb = np.asarray(b.scores.per_window_in(space), dtype=float)
    ia = [i for i, _ in pairs]
    ib = [j for _, j in pairs]
    units, at = record_units(a), ia
    if units.source == "none":
        units, at = record_units(b), ib
    if units.source == "none":
        return pa[ia], pb[ib], None
    return pa[ia], pb[ib], units.take(at)


def separated(lo: float, hi: float) -> bool:
    """True when an interval excludes 0 (NaN intervals never separate anything)."""
    return (lo > 0.0 or hi < 0.0) and not (math.isnan(lo) or math.isnan(hi))
