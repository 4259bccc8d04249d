"""Encoder rankings per backbone x suite: means over releases and seeds, hierarchical intervals,
tie bands.

Pure functions over arrays first (`paired_bootstrap`, `top_tier_mask`, `seed_winner_index`),
then `rank_encoders` / `rank_all`, which turn stored records into `Ranking`s.

Interval method (stated in the report, in the words of bench.analysis.hierarchy.levels_text):
a paired hierarchical bootstrap that draws releases, seeds within a release, held-out episodes
and windows within an episode, once per replicate for every encoder of a backbone x suite, so
encoder differences are paired on the same releases, seeds, episodes and windows. Percentile
intervals, `n_resamples` replicates, fixed `random_seed`. Cells of different releases are never
pooled silently: each is its own (release, seed) cell of the draw.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np
import scipy.stats

from bench.analysis.hierarchy import (Units, components, episode_means, expand, levels_text,
                                      percentile, replicate_means, t_expansion, windows_as_units)
from bench.grid.kinds import GRAFT
from bench.results.record import NORMALIZED, RAW

METRICS = (NORMALIZED, RAW)
PRIMARY = NORMALIZED
DEFAULT_RESAMPLES = 2000
CONFIDENCE = 0.95


class WindowMismatchError(ValueError):
    """Cells of one backbone x suite were scored on different held-out windows."""


# ---------------------------------------------------------------------------------------------
# Pure statistics over arrays


@dataclass
class BootstrapResult:
    """Per-encoder arrays, each (E,): mean over seeds, its interval, paired diff vs the leader."""

    mean: np.ndarray
    mean_lo: np.ndarray
    mean_hi: np.ndarray
    diff: np.ndarray
    diff_lo: np.ndarray
    diff_hi: np.ndarray


def encoder_means(per_window: np.ndarray, leader: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean over present seeds of window means, and mean paired difference vs `leader`.

    per_window: (E, S, W) float with NaN rows where encoder e has no seed s; trailing batch
    axes are allowed after W is reduced, i.e. input (E, S, ..., W). Returns two (E, ...) arrays;
    the difference averages only seeds both encoders have (NaN where they share none)."""
    seed_means = per_window.mean(axis=-1)  # (E, S, ...)
    present = np.isfinite(seed_means)
    filled = np.where(present, seed_means, 0.0)
    n_present = present.sum(axis=1)
    means = filled.sum(axis=1) / np.where(n_present > 0, n_present, np.nan)
    common = present & present[leader][None]
    n_common = common.sum(axis=1)
    diffs = np.where(common, filled - filled[leader][None], 0.0).sum(axis=1)
    diffs = diffs / np.where(n_common > 0, n_common, np.nan)
    return means, diffs


def paired_window_bootstrap(per_window: np.ndarray, leader: int, *,
                            n_resamples: int = DEFAULT_RESAMPLES,
                            confidence_level: float = CONFIDENCE,
                            random_seed: int = 0) -> BootstrapResult:
    """Percentile intervals for encoder means and paired differences vs `leader`.

    per_window: (E, S, W) float, NaN rows for absent (encoder, seed) cells. Window indices are
    resampled once per replicate and shared by every present row (scipy paired bootstrap).
    With W < 2 the intervals are NaN."""
    per_window = np.asarray(per_window, dtype=float)
    n_enc, n_seed, n_win = per_window.shape
    means, diffs = encoder_means(per_window, leader)
    nan = np.full(n_enc, np.nan)
    if n_win < 2:
        return BootstrapResult(means, nan, nan.copy(), diffs, nan.copy(), nan.copy())
    rows = [(e, s) for e in range(n_enc) for s in range(n_seed)
            if np.all(np.isfinite(per_window[e, s]))]

    def statistic(*samples: np.ndarray, axis: int = -1) -> np.ndarray:
        batch = samples[0].shape[:-1]
        grid = np.full((n_enc, n_seed) + batch + (1,), np.nan)
        for (e, s), sample in zip(rows, samples):
            grid[e, s] = np.mean(sample, axis=axis)[..., None]
        m, d = encoder_means(grid, leader)
        return np.concatenate([m, np.nan_to_num(d)], axis=0)

    data = tuple(per_window[e, s] for e, s in rows)
    result = scipy.stats.bootstrap(data, statistic, paired=True, vectorized=True,
                                   n_resamples=n_resamples, confidence_level=confidence_level,
                                   method="percentile", rng=np.random.default_rng(random_seed))
    lo = np.asarray(result.confidence_interval.low)
    hi = np.asarray(result.confidence_interval.high)
    no_common = ~np.isfinite(diffs)
    diff_lo, diff_hi = lo[n_enc:].copy(), hi[n_enc:].copy()
    diff_lo[no_common] = np.nan
    diff_hi[no_common] = np.nan
    return BootstrapResult(means, lo[:n_enc], hi[:n_enc], diffs, diff_lo, diff_hi)


def paired_bootstrap(values: np.ndarray, units: Units, leader: int, *,
                     n_resamples: int = DEFAULT_RESAMPLES, confidence_level: float = CONFIDENCE,
                     random_seed: int = 0) -> BootstrapResult:
    """Percentile intervals for encoder means and paired differences vs `leader`, drawing
    releases, seeds, episodes and windows (bench.analysis.hierarchy).

    values: (E, R, S, W) float, NaN rows for absent (encoder, release, seed) cells; windows
    aligned across cells and grouped into episodes by `units`. With one window, NaN intervals."""
    values = np.asarray(values, dtype=float)
    reps = replicate_means(values, units, n_resamples=n_resamples, random_seed=random_seed)
    diffs = reps.point - reps.point[leader]
    nan = np.full(len(reps.point), np.nan)
    if values.shape[-1] < 2:
        return BootstrapResult(reps.point, nan, nan.copy(), diffs, nan.copy(), nan.copy())
    per_episode = episode_means(values, units)  # (E, R, S, K)
    lo, hi = expand(reps.point, *percentile(reps.draws, confidence_level),
                    small_sample_factors(per_episode, confidence_level))
    d_lo, d_hi = expand(diffs, *percentile(reps.draws - reps.draws[leader][None],
                                           confidence_level),
                        small_sample_factors(per_episode - per_episode[leader][None],
                                             confidence_level))
    return BootstrapResult(reps.point, lo, hi, diffs, d_lo, d_hi)


def small_sample_factors(tables: np.ndarray, confidence_level: float = CONFIDENCE) -> np.ndarray:
    """(E,) t-expansion factors (bench.analysis.hierarchy.t_expansion) of each row's
    (R, S, K) table of per-episode scores, on its Satterthwaite degrees of freedom; a table with
    absent cells on the top varying level's units - 1."""
    out = np.ones(len(tables))
    for i, table in enumerate(tables):
        if np.all(np.isfinite(table)):
            df = components(table).df
        else:
            present = np.isfinite(table).all(axis=-1)  # (R, S)
            n_r, n_s = present.any(axis=1).sum(), present.sum(axis=1).max()
            df = max((n_r if n_r > 1 else n_s if n_s > 1 else table.shape[-1]) - 1, 1)
        out[i] = t_expansion(df, confidence_level)
    return out


def top_tier_mask(diff_lo: np.ndarray, diff_hi: np.ndarray, leader: int) -> np.ndarray:
    """(E,) bool: the leader, and every encoder whose paired-difference interval contains 0."""
    lo, hi = np.asarray(diff_lo, dtype=float), np.asarray(diff_hi, dtype=float)
    with np.errstate(invalid="ignore"):
        mask = (lo <= 0.0) & (hi >= 0.0)
    mask[leader] = True
    return mask


def seed_winner_index(seed_means: np.ndarray) -> np.ndarray:
    """(S,) int: per seed, the encoder row with the lowest MSE; -1 where no encoder has it.

    seed_means: (E, S) float, NaN where absent. Ties go to the lower row index."""
    seed_means = np.asarray(seed_means, dtype=float)
    filled = np.where(np.isfinite(seed_means), seed_means, np.inf)
    winners = filled.argmin(axis=0)
    winners[~np.isfinite(filled.min(axis=0))] = -1
    return winners


# ---------------------------------------------------------------------------------------------
# Records -> rankings


@dataclass
class EncoderResult:
    """One encoder on one backbone x suite. Values are MSE; `diff` is encoder minus leader.
    per_seed: metric -> cell -> MSE, the cell a seed (one release) or 'rel<r>-seed<s>'."""

    encoder: str
    rank: int
    seeds: list[int]
    per_seed: dict[str, dict]  # metric -> cell key -> MSE
    mean: dict[str, float]
    ci: dict[str, tuple[float, float]]
    diff: dict[str, float]
    diff_ci: dict[str, tuple[float, float]]
    in_top_tier: bool
    releases: list[int] = field(default_factory=lambda: [0])


@dataclass
class Ranking:
    """Graft encoders of one backbone x suite, best (lowest mean normalised MSE) first."""

    backbone: str
    suite: str
    encoders: list[EncoderResult] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)
    n_windows: int = 0
    seed_winners: dict = field(default_factory=dict)  # cell key -> its best encoder
    error: str | None = None
    releases: list[int] = field(default_factory=lambda: [0])
    n_episodes: int = 0
    episodes_from: str = "record"  # bench.analysis.hierarchy.Units.source ('none': windows)
    interval: str = ""  # the levels the intervals draw (bench.analysis.hierarchy.levels_text)

    @property
    def leader(self) -> str | None:
        return self.encoders[0].encoder if self.encoders else None

    @property
    def top_tier(self) -> list[str]:
        return [e.encoder for e in self.encoders if e.in_top_tier]

    @property
    def seed_sensitive(self) -> bool:
        """True when different cells (seeds, or release x seed) are won by different encoders."""
        return len(set(self.seed_winners.values())) > 1

    def to_dict(self) -> dict:
        out = asdict(self)
        out.update(leader=self.leader, top_tier=self.top_tier, seed_sensitive=self.seed_sensitive)
        return out


def align_windows(cells: Sequence[dict]) -> tuple[list[int], list[np.ndarray]]:
    """Window ids of the first cell and each cell's per-window index order matching them.

    Raises WindowMismatchError naming both cells when a cell's window ids differ as a set."""
    reference = cells[0]
    ref_ids = [int(w) for w in reference.scores.window_ids]
    position = {w: i for i, w in enumerate(ref_ids)}
    orders = []
    for cell in cells:
        ids = [int(w) for w in cell.scores.window_ids]
        if len(ids) != len(ref_ids) or set(ids) != set(ref_ids):
            extra = sorted(set(ids) - set(ref_ids))[:5]
            absent = sorted(set(ref_ids) - set(ids))[:5]
            raise WindowMismatchError(
                f"{cell.cell_id} was scored on other held-out windows than "
                f"{reference.cell_id} (extra ids {extra}, absent ids {absent}); all cells of a "
                f"backbone x suite must share the protocol's split (compare protocol_hash)")
        order = np.empty(len(ids), dtype=int)
        for i, w in enumerate(ids):
            order[position[w]] = i
        orders.append(order)
    return ref_ids, orders


def record_units(record) -> Units:
    """The episodes a record's windows come from (its window order): stored ids; for records
    made before they were, the task ids where the protocol held out one episode per task (then
    the task is the episode); else each window its own unit."""
    sc = record.scores
    if sc.window_episode is not None:
        return Units(np.asarray(sc.window_episode), np.asarray(sc.window_task))
    held = (record.measured.protocol or {}).get("heldout_episodes_per_task")
    if sc.window_task is not None and held == 1:
        return Units(np.asarray(sc.window_task), np.asarray(sc.window_task), source="task")
    return windows_as_units(sc.n_windows)


def cell_key(release: int, seed: int, releases: Sequence[int]) -> int | str:
    """A cell's key in per-cell tables: its seed when one release is measured, else
    'rel<r>-seed<s>'."""
    return int(seed) if len(releases) == 1 else f"rel{release}-seed{seed}"


@dataclass
class CellArrays:
    """Cells of one backbone x suite by item, release and seed: values[metric] (I, R, S, W)
    with NaN for absent cells, windows in the first cell's order, grouped by `units`."""

    items: list[str]
    releases: list[int]
    seeds: list[int]
    window_ids: list[int]
    units: Units
    values: dict[str, np.ndarray]


def cell_arrays(cells: Sequence, item_of, metrics: Sequence[str] = METRICS) -> CellArrays:
    """Stack records (`item_of(record)` names each one's item) into CellArrays; raises
    WindowMismatchError when their held-out windows differ."""
    window_ids, orders = align_windows(cells)
    items = sorted({item_of(c) for c in cells})
    releases = sorted({int(c.release) for c in cells})
    seeds = sorted({int(c.seed) for c in cells})
    shape = (len(items), len(releases), len(seeds), len(window_ids))
    values = {m: np.full(shape, np.nan) for m in metrics}
    for cell, order in zip(cells, orders):
        at = (items.index(item_of(cell)), releases.index(int(cell.release)),
              seeds.index(int(cell.seed)))
        for m in metrics:
            values[m][at] = np.asarray(cell.scores.per_window_in(m), dtype=float)[order]
    units = record_units(cells[0])
    return CellArrays(items, releases, seeds, window_ids, units, values)


def paired_records_bootstrap(pairs: Sequence[tuple], *, leader: int = 0,
                             n_resamples: int = DEFAULT_RESAMPLES,
                             random_seed: int = 0) -> BootstrapResult:
    """Rows from tuples of records (pairs, triples...), each tuple one (release, seed) cell keyed
    by its first record: row i the tuples' i-th records, on normalised MSE, differences against
    row `leader`, windows aligned by id (WindowMismatchError when they differ), through
    paired_bootstrap (the same draws for every `leader` at one random_seed)."""
    rows = len(pairs[0])
    cells = [t[i] for i in range(rows) for t in pairs]
    _, orders = align_windows(cells)
    values = [np.asarray(c.scores.per_window_in(NORMALIZED), dtype=float)[o]
              for c, o in zip(cells, orders)]
    releases = sorted({int(t[0].release) for t in pairs})
    seeds = sorted({int(t[0].seed) for t in pairs})
    per_window = np.full((rows, len(releases), len(seeds), len(values[0])), np.nan)
    for j, t in enumerate(pairs):
        at = releases.index(int(t[0].release)), seeds.index(int(t[0].seed))
        for i in range(rows):
            per_window[(i, *at)] = values[i * len(pairs) + j]
    return paired_bootstrap(per_window, record_units(cells[0]), leader=leader,
                            n_resamples=n_resamples, random_seed=random_seed)


def graft_records(records: Sequence[dict], backbone: str, suite: str) -> list[dict]:
    return [r for r in records if r.kind == GRAFT and r.backbone == backbone
            and r.suite == suite]


def rank_encoders(records: Sequence[dict], backbone: str, suite: str, *,
                  n_resamples: int = DEFAULT_RESAMPLES, random_seed: int = 0) -> Ranking:
    """Rank the graft cells of `backbone` x `suite` by mean normalised MSE over releases and
    seeds."""
    ranking = Ranking(backbone=backbone, suite=suite)
    cells = graft_records(records, backbone, suite)
    if not cells:
        ranking.error = "no graft cells"
        return ranking
    ca = cell_arrays(cells, lambda c: c.encoder)
    encoders, releases, seeds = ca.items, ca.releases, ca.seeds
    ranking.seeds, ranking.releases, ranking.n_windows = seeds, releases, len(ca.window_ids)
    ranking.n_episodes, ranking.episodes_from = len(ca.units.episodes), ca.units.source
    ranking.interval = levels_text(len(releases), len(seeds), ca.units)
    cell_means = {m: ca.values[m].mean(axis=-1) for m in METRICS}  # (E, R, S)
    point = np.nanmean(cell_means[PRIMARY].reshape(len(encoders), -1), axis=1)
    order_idx = sorted(range(len(encoders)), key=lambda i: (point[i], encoders[i]))
    leader = order_idx[0]
    boot = {m: paired_bootstrap(ca.values[m], ca.units, leader, n_resamples=n_resamples,
                                random_seed=random_seed) for m in METRICS}
    tier = top_tier_mask(boot[PRIMARY].diff_lo, boot[PRIMARY].diff_hi, leader)
    keys = [(r, s) for r in releases for s in seeds]
    flat = {m: cell_means[m].reshape(len(encoders), -1) for m in METRICS}  # (E, R*S)
    for rank, i in enumerate(order_idx, start=1):
        present = [j for j in range(len(keys)) if np.isfinite(flat[PRIMARY][i, j])]
        ranking.encoders.append(EncoderResult(
            encoder=encoders[i], rank=rank,
            seeds=sorted({keys[j][1] for j in present}),
            per_seed={m: {cell_key(*keys[j], releases): float(flat[m][i, j]) for j in present}
                      for m in METRICS},
            mean={m: float(boot[m].mean[i]) for m in METRICS},
            ci={m: (float(boot[m].mean_lo[i]), float(boot[m].mean_hi[i])) for m in METRICS},
            diff={m: float(boot[m].diff[i]) for m in METRICS},
            diff_ci={m: (float(boot[m].diff_lo[i]), float(boot[m].diff_hi[i])) for m in METRICS},
            in_top_tier=bool(tier[i]),
            releases=sorted({keys[j][0] for j in present})))
    winners = seed_winner_index(flat[PRIMARY])
    ranking.seed_winners = {cell_key(*keys[j], releases): encoders[w]
                            for j, w in enumerate(winners) if w >= 0}
    return ranking


def backbone_order(backbones: Sequence[str]) -> list[str]:
    """Backbones smallest first (the registry's parameter counts; within a family, the tiny
    ladder's sizes by rung), unknown ones after, by name."""
    from backbones import BACKBONES  # plain dataclasses: no adapter is imported
    from backbones.tiny_sizes import RUNGS, size_of

    def size(b: str) -> tuple[float, int]:
        entry, rung = BACKBONES.get(b), size_of(b)
        return (entry.params if entry is not None else float("inf"),
                RUNGS.index(rung.rung) if rung is not None else len(RUNGS))

    return sorted(set(backbones), key=lambda b: (size(b), b))


def rank_all(records: Sequence[dict], *, n_resamples: int = DEFAULT_RESAMPLES,
             random_seed: int = 0) -> list[Ranking]:
    """One Ranking per backbone x suite that has graft cells (mismatches become `error`)."""
    rankings = []
    pairs = sorted({(r.backbone, r.suite) for r in records if r.kind == GRAFT})
    order = backbone_order([b for b, _ in pairs])
    for backbone, suite in sorted(pairs, key=lambda p: (p[1], order.index(p[0]))):
        try:
            rankings.append(rank_encoders(records, backbone, suite, n_resamples=n_resamples,
                                          random_seed=random_seed))
        except WindowMismatchError as err:
            rankings.append(Ranking(backbone=backbone, suite=suite, error=str(err)))
    return rankings
