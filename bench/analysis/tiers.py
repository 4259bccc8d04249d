"""A cheaper tier against the full graft, per backbone x suite: rank agreement with intervals.

The items are the encoders that have both a defined score of the cheaper tier (a screen proxy:
higher is better; a short graft: -its MSE, mean over seeds) and at least one graft record on the
backbone x suite. The graft's score of an
encoder is its normalised held-out MSE averaged over its seeds, per window, so the paired window
bootstrap (bench.analysis.agreement.bootstrap_agreement) draws the same windows for every
encoder. Fewer than MIN_ENCODERS such encoders: "not measured", with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from bench.analysis.agreement import (Agreement, Interval, Measure, Undefined, agreement,
                                      bootstrap_agreement, is_defined)
from bench.analysis.rankings import PRIMARY
from bench.grid.kinds import GRAFT, SHORT_GRAFT, get_kind

MIN_ENCODERS = 6


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


def tier_agreement(scores: Mapping[str, Measure], records: Sequence, backbone: str, suite: str,
                   tier: str, n_resamples: int = 1000, seed: int = 0,
                   scores_per_window: Mapping[str, np.ndarray] | None = None) -> TierAgreement:
    """Agreement of the cheaper tier's `scores` {encoder: score, higher is better} with the
    graft records of backbone x suite, with paired window bootstrap intervals.
    `scores_per_window` {encoder: (W,)}, higher is better, on the graft's windows: a tier scored
    per window (a short graft), resampled with the graft's windows instead of held fixed."""
    out = TierAgreement(backbone, suite, tier)
    per_window, problem = graft_per_window(records, backbone, suite)
    if problem:
        out.missing = problem
        return out
    for encoder in sorted(set(scores) | set(per_window)):
        score = scores.get(encoder)
        if encoder not in per_window:
            out.left_out[encoder] = "no graft record"
        elif score is None:
            out.left_out[encoder] = f"no {tier} score"
        elif not is_defined(score):
            out.left_out[encoder] = f"{tier} {score}"
        else:
            out.encoders.append(encoder)
    if len(out.encoders) < MIN_ENCODERS:
        out.missing = (f"not measured: {len(out.encoders)} encoder(s) have both the {tier} score "
                       f"and a graft on {backbone} x {suite} ({out.encoders}); needs "
                       f"{MIN_ENCODERS}")
        return out
    out.predicted = [float(scores[e]) for e in out.encoders]
    windows = np.array([per_window[e] for e in out.encoders])  # (n, W)
    out.graft_mse = windows.mean(axis=1).tolist()
    out.point = agreement(out.predicted, [-m for m in out.graft_mse])
    predicted = (np.array([scores_per_window[e] for e in out.encoders])
                 if scores_per_window is not None else np.array(out.predicted))
    out.intervals = bootstrap_agreement(predicted, -windows, n_resamples, seed)
    return out


def short_tier(variant: str) -> str:
    """The tier's name in tables: short_1_8."""
    return get_kind(SHORT_GRAFT).tag.format(variant=variant)


def short_graft_agreement(records: Sequence, backbone: str, suite: str, variant: str,
                          n_resamples: int = 1000, seed: int = 0) -> TierAgreement:
    """The short-graft tier at `variant` against the full graft: score -MSE (mean over seeds),
    per window when both were scored on the same windows (the paired bootstrap draws both)."""
    tier = short_tier(variant)
    short, problem = graft_per_window(records, backbone, suite, SHORT_GRAFT, variant)
    if problem:
        return TierAgreement(backbone, suite, tier, missing=problem)
    grafts = [r for r in records if r.kind == GRAFT and (r.backbone, r.suite) == (backbone, suite)]
    shorts = [r for r in records if r.kind == SHORT_GRAFT and r.variant == variant
              and (r.backbone, r.suite) == (backbone, suite)]
    if grafts and shorts and grafts[0].scores.window_ids != shorts[0].scores.window_ids:
        return TierAgreement(backbone, suite, tier, missing=(
            f"{shorts[0].cell_id} was scored on other windows than {grafts[0].cell_id}: "
            "not paired, no agreement computed"))
    return tier_agreement({e: -float(v.mean()) for e, v in short.items()}, records, backbone,
                          suite, tier, n_resamples, seed, {e: -v for e, v in short.items()})
