"""The robustness tier's analysis: per backbone x suite, each encoder's MSE under every
perturbation, its degradation relative to its clean MSE with paired hierarchical intervals,
a robustness ranking with its tie band, whether the clean winner stays the winner per kind, and
the transfer question (does the small backbone's most robust encoder stay the most robust on the
large one?). Pure functions of stored records (bench.results.record, bench.results.robust).

The robustness ranking leads with what a user deploys: the perturbed MSE (mean over every
perturbation all grafts have), lowest first, with paired intervals and a tie band. The relative
degradation is ranked beside it (`degradation_ranking`), never in its place: a graft with nothing
to lose (`blind`, whose features ignore the image) degrades by 0 while predicting worst.

Degradation of one cell under one perturbation, per window w: (perturbed_w - clean_w) / clean,
`clean` the cell's clean MSE over the same windows; its mean over windows is the relative
degradation ((perturbed - clean) / clean), averaged over releases and seeds. Intervals are the
rankings' (bench.analysis.rankings.paired_bootstrap): releases, seeds within them, the held-out
episodes the robustness windows come from and their windows, drawn once per replicate for every
row; the clean level is held fixed (its own uncertainty is the rankings').
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from bench.analysis.hierarchy import Units
from bench.analysis.rankings import (DEFAULT_RESAMPLES, PRIMARY, backbone_order,
                                     paired_bootstrap, record_units, top_tier_mask)
from bench.analysis.transfer import rank_agreement
from bench.grid.kinds import GRAFT, column_label
from bench.results.record import Record
from bench.results.robust import RobustRecord


@dataclass
class Degradation:
    """One row (an encoder, native or native_wrapped) under one perturbation."""

    row: str
    perturbation: str  # "kind:severity"
    mse: float  # perturbed MSE, mean over releases and seeds
    clean: float  # clean MSE on the same windows, mean over releases and seeds
    relative: float  # mean relative degradation
    ci: tuple[float, float]


@dataclass
class RobustnessTable:
    """One backbone x suite: rows (grafts by encoder first, then native, native_wrapped)."""

    backbone: str
    suite: str
    rows: list[str] = field(default_factory=list)
    perturbations: list[str] = field(default_factory=list)  # "kind:severity", table order
    params: dict[str, dict] = field(default_factory=dict)
    cells: dict[tuple[str, str], Degradation] = field(default_factory=dict)
    # (row, mean perturbed MSE, its interval, in the leader's tie band), lowest MSE first
    ranking: list[tuple[str, float, tuple[float, float], bool]] = field(default_factory=list)
    # the same by mean relative degradation, least first: beside the ranking, not its lead
    degradation_ranking: list[tuple[str, float, tuple[float, float], bool]] = field(
        default_factory=list)
    clean_winner: str | None = None
    winners: dict[str, dict[int, str]] = field(default_factory=dict)  # kind -> severity -> row
    n_windows: int = 0
    seeds: list[int] = field(default_factory=list)
    releases: list[int] = field(default_factory=list)
    n_episodes: int = 0  # held-out episodes the windows come from (0: not known, windows drawn)
    stale: list[str] = field(default_factory=list)

    @property
    def most_robust(self) -> str | None:
        """The graft with the lowest perturbed MSE (the ranking's lead)."""
        return self.ranking[0][0] if self.ranking else None

    @property
    def least_degraded(self) -> str | None:
        return self.degradation_ranking[0][0] if self.degradation_ranking else None

    def stays(self, kind: str) -> bool | None:
        """Whether the clean winner is the winner under `kind` at every severity measured."""
        won = self.winners.get(kind)
        return None if not won or self.clean_winner is None else all(
            w == self.clean_winner for w in won.values())

    def to_dict(self) -> dict:
        return {"backbone": self.backbone, "suite": self.suite, "rows": self.rows,
                "perturbations": self.perturbations, "params": self.params,
                "degradation": [vars(d) for d in self.cells.values()],
                "ranking": self.ranking, "degradation_ranking": self.degradation_ranking,
                "clean_winner": self.clean_winner, "winners": self.winners,
                "most_robust": self.most_robust, "least_degraded": self.least_degraded,
                "n_windows": self.n_windows, "n_episodes": self.n_episodes,
                "releases": self.releases, "seeds": self.seeds, "stale": self.stale}


def _pairs(records: Sequence[Record], robust: Sequence[RobustRecord], backbone: str, suite: str,
           stale: list[str]) -> list[tuple[str, Record, RobustRecord]]:
    """(row, cell record, its current robustness record) of one backbone x suite."""
    by_id = {r.cell_id: r for r in records}
    out = []
    for rr in robust:
        rec = by_id.get(rr.cell_id)
        if rr.backbone != backbone or rr.suite != suite or rec is None:
            continue
        if not rr.is_for(rec):
            stale.append(rr.cell_id)
            continue
        row = column_label(rec)
        if row is not None:
            out.append((row, rec, rr))
    return out


def _arrays(pairs, rows: list[str], releases: list[int], seeds: list[int], labels: list[str]):
    """per-window perturbed errors (P, E, R, S, W), clean errors (E, R, S, W), NaN where absent,
    and the episodes of the W windows."""
    windows = pairs[0][2].window_ids
    shape = (len(rows), len(releases), len(seeds), len(windows))
    clean = np.full(shape, np.nan)
    perturbed = np.full((len(labels),) + shape, np.nan)
    for row, rec, rr in pairs:
        if rr.window_ids != windows:
            continue  # another window subset: cannot be paired
        at = rows.index(row), releases.index(int(rec.release)), seeds.index(int(rec.seed))
        position = {w: i for i, w in enumerate(rec.scores.window_ids)}
        full = np.asarray(rec.scores.per_window_in(PRIMARY), dtype=float)
        clean[at] = full[[position[w] for w in windows]]
        for e in rr.entries:
            label = f"{e.kind}:{e.severity}"
            if label in labels:
                perturbed[(labels.index(label), *at)] = e.per_window[PRIMARY]
    return perturbed, clean, _window_units(pairs[0][1], windows)


def _window_units(record: Record, windows: list[int]) -> Units:
    """The episodes (and tasks) of the robustness windows, a subset of the cell's."""
    units = record_units(record)
    position = {w: i for i, w in enumerate(record.scores.window_ids)}
    return units.take([position[w] for w in windows])


def _degradation(perturbed: np.ndarray, clean: np.ndarray) -> np.ndarray:
    """(..., R, S, W) per-window relative degradation against each cell's clean mean."""
    return (perturbed - clean) / clean.mean(axis=-1, keepdims=True)


def robustness_table(records: Sequence[Record], robust: Sequence[RobustRecord], backbone: str,
                     suite: str, clean_winner: str | None = None, *,
                     n_resamples: int = DEFAULT_RESAMPLES, random_seed: int = 0
                     ) -> RobustnessTable:
    """Everything the report says about one backbone x suite's robustness (module docstring)."""
    table = RobustnessTable(backbone, suite, clean_winner=clean_winner)
    pairs = _pairs(records, robust, backbone, suite, table.stale)
    if not pairs:
        return table
    grafts = sorted({row for row, rec, _ in pairs if rec.kind == GRAFT})
    table.rows = grafts + sorted({row for row, rec, _ in pairs if rec.kind != GRAFT})
    table.seeds = sorted({int(rec.seed) for _, rec, _ in pairs})
    table.releases = sorted({int(rec.release) for _, rec, _ in pairs})
    entries = {(e.kind, e.severity): e.perturbation for _, _, rr in pairs for e in rr.entries}
    order = _kind_order([rr for _, _, rr in pairs])
    keys = sorted(entries, key=lambda k: (order.index(k[0]), k[1]))
    table.perturbations = [f"{k}:{s}" for k, s in keys]
    table.params = {f"{k}:{s}": entries[(k, s)]["params"] for k, s in keys}
    perturbed, clean, units = _arrays(pairs, table.rows, table.releases, table.seeds,
                                      table.perturbations)
    table.n_windows = clean.shape[-1]
    table.n_episodes = 0 if units.source == "none" else len(units.episodes)
    degradation = _degradation(perturbed, clean)
    boot = dict(units=units, n_resamples=n_resamples, random_seed=random_seed)
    for p, label in enumerate(table.perturbations):
        result = paired_bootstrap(degradation[p], leader=0, **boot)
        for r, row in enumerate(table.rows):
            if np.isfinite(perturbed[p, r]).any():
                table.cells[(row, label)] = Degradation(
                    row, label, float(np.nanmean(perturbed[p, r].mean(axis=-1))),
                    float(np.nanmean(clean[r].mean(axis=-1))), float(result.mean[r]),
                    (float(result.mean_lo[r]), float(result.mean_hi[r])))
    table.ranking = _ranking(perturbed[:, : len(grafts)], grafts, boot)
    table.degradation_ranking = _ranking(degradation[:, : len(grafts)], grafts, boot)
    table.winners = _winners(perturbed[:, : len(grafts)], grafts, keys)
    return table


def _kind_order(robust: Sequence[RobustRecord]) -> list[str]:
    """Kinds in the order the records list them (the table's order when they were measured)."""
    return list(dict.fromkeys(e.kind for rr in robust for e in rr.entries))


def _ranking(per_window: np.ndarray, grafts: list[str], boot: dict):
    """Grafts by a (P, E, R, S, W) per-window score (perturbed MSE or relative degradation) averaged
    over every perturbation all of them have, lowest first, with its interval and whether it is
    in the leader's tie band (paired difference interval contains 0)."""
    if not grafts:
        return []
    with np.errstate(all="ignore"), warnings.catch_warnings():  # an absent row is NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        complete = [p for p in range(len(per_window)) if np.isfinite(
            np.nanmean(per_window[p], axis=(1, 2, 3))).all()]
        if not complete:
            return []
        score = per_window[complete].mean(axis=0)  # (E, R, S, W): mean over perturbations
        point = np.nanmean(score.mean(axis=-1), axis=(1, 2))
    leader = int(np.nanargmin(point))
    result = paired_bootstrap(score, leader=leader, **boot)
    tier = top_tier_mask(result.diff_lo, result.diff_hi, leader)
    order = sorted(range(len(grafts)), key=lambda i: (result.mean[i], grafts[i]))
    return [(grafts[i], float(result.mean[i]), (float(result.mean_lo[i]),
             float(result.mean_hi[i])), bool(tier[i])) for i in order]


def _winners(perturbed: np.ndarray, grafts: list[str], keys) -> dict[str, dict[int, str]]:
    """kind -> severity -> the graft with the lowest perturbed MSE (mean over releases, seeds)."""
    winners: dict[str, dict[int, str]] = {}
    for p, (kind, severity) in enumerate(keys):
        means = np.nanmean(perturbed[p].mean(axis=-1), axis=(1, 2)) if grafts else np.array([])
        if len(means) and np.isfinite(means).any():
            winners.setdefault(kind, {})[severity] = grafts[int(np.nanargmin(means))]
    return winners


def robustness_all(records: Sequence[Record], robust: Sequence[RobustRecord],
                   clean_winners: dict[tuple[str, str], str], **boot) -> list[RobustnessTable]:
    """One table per backbone x suite with robustness records, small backbone first."""
    pairs = sorted({(rr.backbone, rr.suite) for rr in robust})
    order = backbone_order([b for b, _ in pairs])
    pairs.sort(key=lambda p: (p[1], order.index(p[0])))
    return [robustness_table(records, robust, b, s, clean_winners.get((b, s)), **boot)
            for b, s in pairs]


def robustness_transfer(tables: Sequence[RobustnessTable]) -> list[dict]:
    """Per suite and pair of backbones (small, large): each one's most robust graft, whether
    they are the same, and the rank agreement of the robustness scores they share."""
    out = []
    for suite in sorted({t.suite for t in tables}):
        mine = [t for t in tables if t.suite == suite and t.ranking]
        order = backbone_order([t.backbone for t in mine])
        mine.sort(key=lambda t: order.index(t.backbone))
        for i, small in enumerate(mine):
            for large in mine[i + 1:]:
                a, b = dict((r[0], r[1]) for r in small.ranking), dict(
                    (r[0], r[1]) for r in large.ranking)
                common = sorted(set(a) & set(b))
                out.append({"suite": suite, "small": small.backbone, "large": large.backbone,
                            "small_most_robust": small.most_robust,
                            "large_most_robust": large.most_robust,
                            "large_tie_band": [r[0] for r in large.ranking if r[3]],
                            "same": small.most_robust == large.most_robust,
                            "encoders": common,
                            "agreement": rank_agreement([a[e] for e in common],
                                                        [b[e] for e in common])})
    return out
