"""A cheaper tier against the full graft, per backbone x suite: rank agreement with intervals.

The items are the encoders that have both a defined score of the cheaper tier (a screen proxy:
higher is better; a short graft: -its MSE, mean over seeds) and at least one graft record on the
backbone x suite. The graft's score of an
encoder is its normalised held-out MSE averaged over its releases and seeds; the paired bootstrap
(bench.analysis.agreement.bootstrap_agreement) draws releases, seeds, held-out episodes and
windows once for every encoder and tier. Fewer than MIN_ENCODERS such encoders: "not
measured", with the reason.

Two sets of items (`item_set`): ALL of them, and the CANDIDATES a team would choose between
(bench.analysis.candidates: pretrained encoders; never random twins or known-answer encoders),
which need MIN_CANDIDATES. Given the naive baselines' scores (bench.screen.proxies: parameter
count, FLOPs, input resolution), a tier also gets its tau-b minus the best baseline's on the
same items, with the interval of that difference on the same replicates as its own statistics;
the screen recommends it only where that interval lies above 0 (`recommended`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Collection, Mapping, Sequence

import numpy as np

from bench.analysis.agreement import (NAIVE_GAP, Agreement, Interval, Measure, Undefined,
                                      agreement, bootstrap_agreement, is_defined, kendall_tau_b,
                                      naive_gap)
from bench.analysis.hierarchy import Units
from bench.analysis.rankings import PRIMARY, record_units
from bench.grid.kinds import GRAFT, SHORT_GRAFT, get_kind

MIN_ENCODERS = 6
# The candidates a team weighs are few (studies/real: 5 pretrained encoders); 4 items give 6 pairs,
# the fewest whose tau-b can tell a fair order from a coin (and its interval says how little).
MIN_CANDIDATES = 4
ALL, CANDIDATES = "all", "candidates"
MIN_ITEMS = {ALL: MIN_ENCODERS, CANDIDATES: MIN_CANDIDATES}


@dataclass
class TierAgreement:
    """One cheaper tier (`tier`) against the graft on backbone x suite; `missing` says why not."""

    backbone: str
    suite: str
    tier: str
    encoders: list[str] = field(default_factory=list)
    predicted: list[float] = field(default_factory=list)
    graft_mse: list[float] = field(default_factory=list)
    point: Agreement | None = None
    intervals: dict[str, Interval | Undefined] = field(default_factory=dict)
    left_out: dict[str, str] = field(default_factory=dict)  # encoder -> why it is not an item
    missing: str | None = None
    item_set: str = ALL  # ALL or CANDIDATES
    # tau-b minus the best naive baseline's on these items (None: no baselines given, or the
    # tier is one); which baseline was best at the point; each baseline's tau-b here.
    naive_gap: Measure | None = None
    best_naive: str | None = None
    naive_tau_b: dict[str, Measure] = field(default_factory=dict)

    @property
    def naive_gap_interval(self) -> Interval | Undefined | None:
        return self.intervals.get(NAIVE_GAP)

    @property
    def recommended(self) -> bool:
        """Beats the best naive baseline: the paired interval of the difference lies above 0."""
        ci = self.naive_gap_interval
        return isinstance(ci, Interval) and ci.low > 0

    def to_dict(self) -> dict:
        """Every field (the report's JSON makes values plain), and `recommended`."""
        return {f.name: getattr(self, f.name) for f in fields(self)} | {
            "recommended": self.recommended}


def graft_per_window(records: Sequence, backbone: str, suite: str, kind: str = GRAFT,
                     variant: str | None = None) -> tuple[dict[str, np.ndarray], str | None]:
    """({encoder: (W,) normalised MSE per window, mean over seeds}, problem or None) of the
    `kind` x `variant` records (the graft's, or a short graft's) on backbone x suite."""
    grafts = [r for r in records if r.kind == kind and r.variant == variant
              and r.backbone == backbone and r.suite == suite]
    if not grafts:
        return {}, None
    windows = grafts[0].scores.window_ids
    for r in grafts:
        if r.scores.window_ids != windows:
            return {}, (f"{r.cell_id} was scored on other windows than {grafts[0].cell_id}: "
                        "not paired, no agreement computed")
    by_encoder: dict[str, list] = {}
    for r in grafts:
        by_encoder.setdefault(r.encoder, []).append(r.scores.per_window_in(PRIMARY))
    return {e: np.mean(v, axis=0) for e, v in by_encoder.items()}, None


def graft_cells(records: Sequence, backbone: str, suite: str, kind: str = GRAFT,
                variant: str | None = None) -> tuple[dict[str, np.ndarray], Units | None]:
    """({encoder: (R, S, W) normalised MSE per window of each (release, seed) cell, NaN where
    absent}, the windows' episodes) of the `kind` x `variant` records on backbone x suite: the
    releases and seeds indexed over every graft and short graft there, so two tiers' arrays
    line up. Windows as graft_per_window checks them (call it first)."""
    here = [r for r in records if r.backbone == backbone and r.suite == suite
            and r.kind in (GRAFT, SHORT_GRAFT)]
    mine = [r for r in here if r.kind == kind and r.variant == variant]
    if not mine:
        return {}, None
    releases = sorted({int(r.release) for r in here})
    seeds = sorted({int(r.seed) for r in here})
    out: dict[str, np.ndarray] = {}
    for r in mine:
        cells = out.setdefault(r.encoder, np.full((len(releases), len(seeds),
                                                  r.scores.n_windows), np.nan))
        cells[releases.index(int(r.release)), seeds.index(int(r.seed))] = \
            r.scores.per_window_in(PRIMARY)
    return out, record_units(mine[0])


def _items(out: TierAgreement, scores: Mapping[str, Measure], per_window: Mapping,
           items: Collection[str] | None) -> None:
    """The tier's items into `out.encoders`, each encoder left out with why into `left_out`."""
    for encoder in sorted(set(scores) | set(per_window)):
        score = scores.get(encoder)
        if encoder not in per_window:
            out.left_out[encoder] = "no graft record"
        elif items is not None and encoder not in items:
            out.left_out[encoder] = f"not among the {out.item_set}"
        elif score is None:
            out.left_out[encoder] = f"no {out.tier} score"
        elif not is_defined(score):
            out.left_out[encoder] = f"{out.tier} {score}"
        else:
            out.encoders.append(encoder)


def _baseline_scores(out: TierAgreement, baselines: Mapping[str, Mapping[str, Measure]]
                     ) -> dict[str, np.ndarray]:
    """{baseline: (n,) scores on the tier's items} of the baselines that score every item (the
    others' tau-b here says why not)."""
    kept = {}
    for name, by_encoder in baselines.items():
        bad = next((f"{e}: {by_encoder.get(e, 'no score')}" for e in out.encoders
                    if not is_defined(by_encoder.get(e, Undefined("no score")))), None)
        if bad is not None:
            out.naive_tau_b[name] = Undefined(f"{name} undefined for {bad}")
            continue
        kept[name] = np.array([float(by_encoder[e]) for e in out.encoders])
    return kept


def tier_agreement(scores: Mapping[str, Measure], records: Sequence, backbone: str, suite: str,
                   tier: str, n_resamples: int = 1000, seed: int = 0,
                   scores_per_window: Mapping[str, np.ndarray] | None = None, *,
                   baselines: Mapping[str, Mapping[str, Measure]] | None = None,
                   items: Collection[str] | None = None, item_set: str = ALL) -> TierAgreement:
    """Agreement of the cheaper tier's `scores` {encoder: score, higher is better} with the
    graft records of backbone x suite, with paired hierarchical bootstrap intervals.
    `scores_per_window` {encoder: (R, S, W)} (graft_cells' index), higher is better: a tier
    scored per window (a short graft), drawn with the graft's cells and windows, not held fixed.
    `baselines` {naive baseline: {encoder: score}}: the tier's tau-b minus the best of theirs,
    point and interval on the same replicates. `items`: only these encoders (the set
    `item_set` names), at least MIN_ITEMS[item_set] of them."""
    out = TierAgreement(backbone, suite, tier, item_set=item_set)
    per_window, problem = graft_per_window(records, backbone, suite)
    if problem:
        out.missing = problem
        return out
    _items(out, scores, per_window, items)
    if len(out.encoders) < MIN_ITEMS[item_set]:
        out.missing = (f"not measured: {len(out.encoders)} encoder(s) have both the {tier} "
                       f"score and a graft on {backbone} x {suite} ({out.encoders}; items: "
                       f"{item_set}); needs {MIN_ITEMS[item_set]}")
        return out
    out.predicted = [float(scores[e]) for e in out.encoders]
    windows = np.array([per_window[e] for e in out.encoders])  # (n, W)
    out.graft_mse = windows.mean(axis=1).tolist()
    by_cell, units = graft_cells(records, backbone, suite)
    cells = np.array([by_cell[e] for e in out.encoders])  # (n, R, S, W)
    actual = [-m for m in out.graft_mse]
    out.point = agreement(out.predicted, actual)
    predicted = (np.array([scores_per_window[e] for e in out.encoders])
                 if scores_per_window is not None else np.array(out.predicted))
    base = None if baselines is None else _baseline_scores(out, baselines)
    if base is not None:
        out.naive_tau_b |= {k: kendall_tau_b(v, actual) for k, v in base.items()}
        out.naive_gap = naive_gap(np.array(out.predicted), np.array(actual), base)
        defined = {k: v for k, v in out.naive_tau_b.items() if is_defined(v)}
        out.best_naive = max(defined, key=defined.get) if defined else None
    out.intervals = bootstrap_agreement(predicted, -cells, n_resamples, seed, baselines=base,
                                        units=units)
    return out


def short_tier(variant: str) -> str:
    """The tier's name in tables: short_1_8."""
    return get_kind(SHORT_GRAFT).tag.format(variant=variant)


def short_graft_agreement(records: Sequence, backbone: str, suite: str, variant: str,
                          n_resamples: int = 1000, seed: int = 0, **kwargs) -> TierAgreement:
    """The short-graft tier at `variant` against the full graft: score -MSE (mean over seeds),
    per window when both were scored on the same windows (the paired bootstrap draws both).
    kwargs: tier_agreement's (baselines, items, item_set)."""
    tier = short_tier(variant)
    item_set = kwargs.get("item_set", ALL)
    short, problem = graft_per_window(records, backbone, suite, SHORT_GRAFT, variant)
    if problem:
        return TierAgreement(backbone, suite, tier, missing=problem, item_set=item_set)
    grafts = [r for r in records if r.kind == GRAFT and (r.backbone, r.suite) == (backbone, suite)]
    shorts = [r for r in records if r.kind == SHORT_GRAFT and r.variant == variant
              and (r.backbone, r.suite) == (backbone, suite)]
    if grafts and shorts and grafts[0].scores.window_ids != shorts[0].scores.window_ids:
        return TierAgreement(backbone, suite, tier, item_set=item_set, missing=(
            f"{shorts[0].cell_id} was scored on other windows than {grafts[0].cell_id}: "
            "not paired, no agreement computed"))
    # per (release, seed) cell, so the draw pairs each short graft with its own graft's cell
    cells, _ = graft_cells(records, backbone, suite, SHORT_GRAFT, variant)
    return tier_agreement({e: -float(v.mean()) for e, v in short.items()}, records, backbone,
                          suite, tier, n_resamples, seed, {e: -v for e, v in cells.items()},
                          **kwargs)


SMALL_MODEL = "small model"


def small_model_tier(small: str, cells_drawn: bool = True) -> str:
    """The rung's name in tables: 'small model smolvla' (its releases and seeds held at their
    mean when they could not be drawn with the large model's)."""
    return f"{SMALL_MODEL} {small}" + ("" if cells_drawn else " (its cells not drawn)")


def small_model_agreement(records: Sequence, small: str, large: str, suite: str,
                          n_resamples: int = 1000, seed: int = 0, **kwargs) -> TierAgreement:
    """"Screen on the small model of the family" as a tier for its large model: the small
    backbone's graft scored -MSE (mean over its releases and seeds) against the large one's
    graft on the same suite's held-out windows. Drawn per window with the large model's cells
    when both hold the same releases x seeds (each small cell paired with the large cell of the
    same index: independent trainings, drawn together), else its mean per window with the
    windows drawn and its cells held (the tier's name says so). kwargs: tier_agreement's."""
    item_set = kwargs.get("item_set", ALL)
    mean, problem = graft_per_window(records, small, suite)
    large_windows = next((r.scores.window_ids for r in records if r.kind == GRAFT
                          and (r.backbone, r.suite) == (large, suite)), None)
    if not problem and mean and large_windows is not None:
        first = next(r for r in records if r.kind == GRAFT and (r.backbone, r.suite)
                     == (small, suite))
        if first.scores.window_ids != large_windows:
            problem = (f"{small} and {large} were scored on other windows of {suite}: not "
                       "paired, no agreement computed")
    if problem:
        return TierAgreement(large, suite, small_model_tier(small), missing=problem,
                             item_set=item_set)
    cells, _ = graft_cells(records, small, suite)
    large_cells, _ = graft_cells(records, large, suite)
    shape = next((v.shape for v in large_cells.values()), None)
    drawn = all(v.shape == shape for v in cells.values())
    per_window = {e: -(v if drawn else mean[e]) for e, v in cells.items()}
    return tier_agreement({e: -float(v.mean()) for e, v in mean.items()}, records, large,
                          suite, small_model_tier(small, drawn), n_resamples, seed, per_window,
                          **kwargs)
