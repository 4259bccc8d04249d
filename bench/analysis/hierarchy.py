"""Intervals over what varies between two trainings of the same choice: a hierarchical bootstrap.

A cell's offline MSE depends on which release of the backbone it was grafted into, on its seed,
on which held-out episodes the suite happened to hold out, and on the windows of each episode.
Every interval of the report draws those four levels, top down (rliable's intervals over runs,
Agarwal et al. 2021, extended to the levels a graft has):

1. releases (independently trained backbones of one recipe), with replacement;
2. seeds within each drawn release, with replacement;
3. held-out episodes, with replacement (within each task when every task holds at least two,
   so the task mix stays the suite's; across tasks otherwise: with one episode per task the task
   is the episode, and which tasks were held out is what varies);
4. windows within each drawn episode, with replacement.

One draw serves every encoder of a backbone x suite (paired): encoders are compared on the same
releases, seeds, episodes and windows. At each level a draw takes n - 1 of the n units (Rao and
Wu's rescaled bootstrap): the plain n-of-n draw shrinks a mean's variance by (n - 1) / n, which
at 2-3 releases or seeds is a third to a half. A level with one unit varies nothing (said in the
interval's text). Percentile intervals; fewer than ~5 units at the top level still undercover
(the bootstrap cannot know a t quantile), so the variance budget (`variance_budget`) says what
more releases, seeds or episodes would buy.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

CONFIDENCE = 0.95
LEVELS = ("release", "seed", "episode", "window")


@dataclass(frozen=True)
class Units:
    """How the held-out windows group: episode (W,) int and task (W,) int per window; `source`
    says where the episode ids came from ('record', or 'task' for records made before windows
    carried them, when each task held out one episode)."""

    episode: np.ndarray
    task: np.ndarray
    source: str = "record"
    # Draw within tasks whatever they hold: for rows that each read one task's windows (a task
    # with one episode keeps it in every draw, its windows drawn within it).
    by_task: bool = False

    @property
    def episodes(self) -> np.ndarray:
        return np.unique(self.episode)

    def take(self, positions) -> "Units":
        """The units of the windows at `positions` (a subset of these windows, in that order)."""
        return Units(self.episode[positions], self.task[positions], self.source, self.by_task)

    @property
    def stratified(self) -> bool:
        """Episodes drawn within tasks: when every task holds at least two, or `by_task`."""
        per_task = [len(np.unique(self.episode[self.task == t])) for t in np.unique(self.task)]
        return self.by_task or min(per_task) >= 2


def windows_as_units(n_windows: int) -> Units:
    """Each window its own episode (no grouping known): the window bootstrap of old."""
    ids = np.arange(n_windows)
    return Units(ids, np.zeros(n_windows, dtype=int), source="none")


def _kept(n: int) -> int:
    """How many of n units a draw takes: n - 1 (Rao and Wu's rescaling), all of one."""
    return max(n - 1, 1)


def _counts(rng: np.random.Generator, draws: np.ndarray, n: int) -> np.ndarray:
    """(B, n) how often each of n units is drawn when replicate b makes draws[b] uniform draws
    with replacement (a sum of multinomials of one probability vector is one multinomial)."""
    return rng.multinomial(np.asarray(draws, dtype=np.int64), np.full(n, 1.0 / n))


def window_weights(units: Units, n_resamples: int, rng: np.random.Generator) -> np.ndarray:
    """(B, W) float: each replicate's weight on every window (episodes drawn, then windows
    within each drawn episode, n - 1 of n at both levels; rows sum to 1)."""
    n_w = len(units.episode)
    if units.stratified:
        groups = [np.unique(units.episode[units.task == t]) for t in np.unique(units.task)]
    else:
        groups = [units.episodes]
    out = np.zeros((n_resamples, n_w))
    for group in groups:
        drawn = _counts(rng, np.full(n_resamples, _kept(len(group))), len(group))  # (B, K)
        for k, episode in enumerate(group):
            rows = np.flatnonzero(units.episode == episode)
            picks = _counts(rng, drawn[:, k] * _kept(len(rows)), len(rows))  # (B, n_e)
            # a drawn episode weighs its number of windows, as in the point estimate
            out[:, rows] += picks * (len(rows) / _kept(len(rows)))
    return out / out.sum(axis=1, keepdims=True)


def cell_weights(n_releases: int, n_seeds: int, n_resamples: int,
                 rng: np.random.Generator) -> np.ndarray:
    """(B, R, S) float: each replicate's weight on every (release, seed) cell (releases drawn,
    then seeds within each drawn release, n - 1 of n at both levels)."""
    releases = _counts(rng, np.full(n_resamples, _kept(n_releases)), n_releases)  # (B, R)
    out = np.zeros((n_resamples, n_releases, n_seeds))
    for r in range(n_releases):
        out[:, r] = _counts(rng, releases[:, r] * _kept(n_seeds), n_seeds)
    return out


@dataclass(frozen=True)
class Replicates:
    """Per-encoder means over cells: `point` (E,) on all data, `draws` (E, B) one per replicate
    (NaN where a replicate drew none of an encoder's cells)."""

    point: np.ndarray
    draws: np.ndarray


def cell_means(values: np.ndarray) -> np.ndarray:
    """(E, R, S) window means of `values` (E, R, S, W), NaN for an absent cell."""
    return np.asarray(values, dtype=float).mean(axis=-1)


def _weighted(means: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(E, ...) weighted mean over the (R, S) axes of `means` (E, R, S, ...) with `weights`
    (R, S, ...) broadcast, absent (NaN) cells left out."""
    present = np.isfinite(means)
    num = np.where(present, means, 0.0) * weights
    den = present * weights
    with np.errstate(invalid="ignore", divide="ignore"):
        return num.sum(axis=(1, 2)) / np.where(den.sum(axis=(1, 2)) > 0, den.sum(axis=(1, 2)),
                                                np.nan)


def replicate_means(values: np.ndarray, units: Units, *, n_resamples: int = 2000,
                    random_seed: int = 0) -> Replicates:
    """Hierarchical replicates of every encoder's mean. values: (E, R, S, W) float per-window
    scores of encoder e on release r, seed s (NaN rows for absent cells), windows aligned
    across cells and grouped by `units`. The same draw for every encoder (paired)."""
    values = np.asarray(values, dtype=float)
    n_enc, n_rel, n_seed, n_win = values.shape
    if len(units.episode) != n_win:
        raise ValueError(f"units cover {len(units.episode)} windows, values hold {n_win}")
    point = _weighted(cell_means(values), np.ones((n_rel, n_seed)))
    rng = np.random.default_rng(random_seed)
    ww = window_weights(units, n_resamples, rng)  # (B, W)
    cw = cell_weights(n_rel, n_seed, n_resamples, rng)  # (B, R, S)
    filled = np.nan_to_num(values)
    per_cell = np.einsum("ersw,bw->ersb", filled, ww)
    per_cell[~np.isfinite(cell_means(values))] = np.nan
    draws = _weighted(per_cell, np.moveaxis(cw, 0, -1))
    return Replicates(point, draws)


def percentile(draws: np.ndarray, confidence: float = CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi), each draws.shape[:-1]: percentile interval over the last axis, NaN ignored."""
    alpha = (1 - confidence) / 2
    with warnings.catch_warnings():  # an all-NaN row (nothing drawn) gives NaN, said by callers
        warnings.simplefilter("ignore", RuntimeWarning)
        return (np.nanquantile(draws, alpha, axis=-1), np.nanquantile(draws, 1 - alpha, axis=-1))


def levels_text(n_releases: int, n_seeds: int, units: Units) -> str:
    """The interval's own words: every level it draws, with its count, and the ones it cannot."""
    n_ep = len(units.episodes)
    if units.source == "none":
        episode = f"{len(units.episode)} held-out windows drawn as independent units (the records "
        episode += "carry no episode ids)"
    else:
        how = "within tasks" if units.stratified else "across tasks"
        src = "" if units.source == "record" else " (one per task: the task ids)"
        episode = f"{n_ep} held-out episodes{src} drawn {how}, then windows within each episode"
    parts = [f"{n_releases} release{'s' if n_releases != 1 else ''}"
             + ("" if n_releases > 1 else " (not drawn: one)"),
             f"{n_seeds} seed{'s' if n_seeds != 1 else ''} within a release"
             + ("" if n_seeds > 1 else " (not drawn: one)"), episode]
    return ("hierarchical bootstrap (n - 1 of n units at each level, percentile) over "
            + "; ".join(parts))


def episode_means(values: np.ndarray, units: Units) -> np.ndarray:
    """(..., K) means over each held-out episode's windows of `values` (..., W), episodes in
    `units.episodes` order."""
    return np.stack([values[..., units.episode == e].mean(axis=-1) for e in units.episodes],
                    axis=-1)


@dataclass(frozen=True)
class Components:
    """Method-of-moments variance components of one (R, S, K) table of per-episode scores
    (release r, seed s within it, held-out episode k; crossed: every cell scores every episode):
    release, seed, episode and residual (episode x cell, windows inside it) variances, the
    variance of the grand mean they add up to, and its Satterthwaite degrees of freedom."""

    release: float
    seed: float
    episode: float
    residual: float
    shape: tuple[int, int, int]
    df: float

    def mean_variance(self, releases: int | None = None, seeds: int | None = None,
                      episodes: int | None = None) -> float:
        """Var of the grand mean at these counts (default: the measured ones)."""
        r, s, k = (releases or self.shape[0]), (seeds or self.shape[1]), (episodes or self.shape[2])
        return (self.release / r + self.seed / (r * s) + self.episode / k
                + self.residual / (r * s * k))

    def shares(self) -> dict[str, float]:
        """Each level's share of the grand mean's variance at the measured counts."""
        r, s, k = self.shape
        parts = {"release": self.release / r, "seed": self.seed / (r * s),
                 "episode": self.episode / k, "episode x training": self.residual / (r * s * k)}
        total = sum(parts.values())
        return {name: (v / total if total > 0 else float("nan")) for name, v in parts.items()}


def components(table: np.ndarray) -> Components:
    """Components of a complete (R, S, K) table (no NaN). A level with one unit has no variance
    of its own here (R = 1: the seeds carry what releases would; S = 1 likewise)."""
    table = np.asarray(table, dtype=float)
    n_r, n_s, n_k = table.shape
    grand = table.mean()
    m_r, m_rs, m_k = table.mean(axis=(1, 2)), table.mean(axis=2), table.mean(axis=(0, 1))
    cells = n_r * n_s
    df_res = (cells - 1) * (n_k - 1)
    ms_res = (((table - m_rs[..., None] - m_k + grand) ** 2).sum() / df_res) if df_res else 0.0
    ms_ep = n_r * n_s * ((m_k - grand) ** 2).sum() / (n_k - 1) if n_k > 1 else 0.0
    ms_seed = (n_k * ((m_rs - m_r[:, None]) ** 2).sum() / (n_r * (n_s - 1))) if n_s > 1 else None
    ms_rel = (n_s * n_k * ((m_r - grand) ** 2).sum() / (n_r - 1)) if n_r > 1 else None
    var_e = ms_res
    var_c = max((ms_ep - ms_res) / cells, 0.0)
    var_b = max(((ms_seed if ms_seed is not None else ms_res) - ms_res) / n_k, 0.0)
    below = ms_seed if ms_seed is not None else ms_res
    var_a = max(((ms_rel if ms_rel is not None else below) - below) / (n_s * n_k), 0.0)
    # Var(grand mean) = (MS_top + MS_ep - MS_res) / (R S K), MS_top the highest cell level that
    # varies; Satterthwaite's df taken on MS_top + MS_ep (a bound on that sum): with the
    # subtracted MS_res in it the df collapses whenever MS_ep ~ MS_res, i.e. when episodes
    # carry nothing beyond the residual.
    terms = [(ms_ep, n_k - 1)]
    if ms_rel is not None:
        terms.append((ms_rel, n_r - 1))
    elif ms_seed is not None:
        terms.append((ms_seed, n_r * (n_s - 1)))
    terms = [(ms, df) for ms, df in terms if df > 0]
    total = sum(ms for ms, _ in terms)
    denominator = sum(ms ** 2 / df for ms, df in terms)
    df = total ** 2 / denominator if total > 0 and denominator > 0 else float("inf")
    return Components(var_a, var_b, var_c, var_e, (n_r, n_s, n_k), float(max(df, 1.0)))


def t_expansion(df: float, confidence: float = CONFIDENCE) -> float:
    """How much wider a t interval on `df` degrees of freedom is than a normal one: the factor a
    percentile bootstrap's half-widths take when its top level has few units (>= 1)."""
    from scipy.stats import norm, t

    if not np.isfinite(df):
        return 1.0
    q = 1 - (1 - confidence) / 2
    return float(max(t.ppf(q, df) / norm.ppf(q), 1.0))


def expand(point: np.ndarray, lo: np.ndarray, hi: np.ndarray, factor: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) with each half-width around `point` multiplied by `factor` (all (E,))."""
    return point - (point - lo) * factor, point + (hi - point) * factor
