"""Tuned encoder against frozen: does training the encoder's weights beside the projector beat
grafting it frozen, per encoder and backbone x suite, and does the encoder ranking change?

A tuned cell is any kind of the table with `tune_encoder` (bench.grid.kinds); its frozen twin is
the cell of the same backbone, suite, encoder and seed that trained the projector alone for the
same number of steps: the graft for a full-length tuned cell, the short_1_8 graft for
tuned_encoder_1_8 (both schedules compressed alike). diff = tuned - frozen on normalised
MSE (negative: tuning helps), averaged over the (release, seed) cells both have, with the
rankings' paired hierarchical bootstrap (releases, seeds, held-out episodes, windows:
bench.analysis.hierarchy). A verdict needs at least two seeds (one seed's difference is one
training's, and training noise moves grafts more than many of the gaps: docs/INTERVALS.md) and
a frozen twin whose loss had flattened (else tuning may only have trained faster).

Where the zero-learning-rate twin (a `live_encoder` kind: the tuned cell's live, full-precision
feature path with the encoder held) ran too, tuned - frozen splits in two on the cells all three
have: twin - frozen, what the live path does against the stored features, and tuned - twin,
what moving the encoder does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from bench.analysis.rankings import (
    DEFAULT_RESAMPLES, WindowMismatchError, backbone_order, paired_records_bootstrap,
)
from bench.grid.kinds import GRAFT, SHORT_GRAFT, kind_of


HELPS, HURTS, UNCLEAR = "tuning helps", "tuning hurts", "no clear difference"
ONE_SEED = "no verdict: one seed (an interval must draw seeds)"
NOT_FLAT = "no verdict: the frozen graft's loss had not flattened"
# The frozen twin's loss has flattened when the mean logged loss of its last quarter of steps
# lies within this fraction below the quarter before (pooled over its cells). The logged losses
# are single batches: a quarter's mean is what is steady enough to compare.
FLAT_TOLERANCE = 0.05


def last_quarter_change(curves: Sequence[Sequence[Sequence[float]]]) -> float:
    """Relative change of the mean logged loss from the third quarter of the steps to the last,
    each quarter's mean averaged over `curves` ([[step, loss], ...] with their last step as the
    end); NaN where a quarter has no logged point."""
    thirds, lasts = [], []
    for curve in curves:
        points = np.asarray(curve, dtype=float)
        if points.ndim != 2 or len(points) == 0:
            return float("nan")
        steps, end = points[:, 0], points[-1, 0] + 1
        third = points[(steps >= end / 2) & (steps < 3 * end / 4), 1]
        last = points[steps >= 3 * end / 4, 1]
        if len(third) == 0 or len(last) == 0:
            return float("nan")
        thirds.append(third.mean())
        lasts.append(last.mean())
    if not thirds:
        return float("nan")
    return float(np.mean(lasts) / np.mean(thirds) - 1.0)


def _verdict(seeds: Sequence[int], ci: tuple[float, float], helps: str, hurts: str) -> str:
    if len(seeds) < 2:
        return ONE_SEED
    lo, hi = ci
    if np.isfinite(hi) and hi < 0:
        return helps
    if np.isfinite(lo) and lo > 0:
        return hurts
    return UNCLEAR


MOVED_HELPS, MOVED_HURTS = "moving the encoder helps", "moving the encoder hurts"
LIVE_HELPS, LIVE_HURTS = "the live path helps", "the live path hurts"


@dataclass
class LiveSplit:
    """tuned - frozen split by the zero-learning-rate twin, on the cells all three have."""

    seeds: list[int]
    frozen_mse: float
    twin_mse: float
    tuned_mse: float
    path: float  # twin - frozen: the live full-precision path against the stored features
    path_ci: tuple[float, float]
    moved: float  # tuned - twin: the encoder's weights moving (and its gradients in the clip)
    moved_ci: tuple[float, float]
    twin_step_s: float = float("nan")

    @property
    def path_verdict(self) -> str:
        return _verdict(self.seeds, self.path_ci, LIVE_HELPS, LIVE_HURTS)

    @property
    def moved_verdict(self) -> str:
        return _verdict(self.seeds, self.moved_ci, MOVED_HELPS, MOVED_HURTS)


@dataclass
class TunedComparison:
    """One encoder on one backbone x suite: tuned minus frozen over the seeds both have."""

    backbone: str
    suite: str
    encoder: str
    steps: int  # training steps of both the tuned cell and its frozen twin
    seeds: list[int]
    frozen_mse: float
    tuned_mse: float
    diff: float  # tuned - frozen, normalised MSE
    diff_ci: tuple[float, float]
    # Train seconds per optimiser step (record timings / steps), mean over the paired seeds: the
    # tuned cell runs and back-propagates its encoder; the frozen one reads stored features.
    tuned_step_s: float = float("nan")
    frozen_step_s: float = float("nan")
    # The frozen twins' last quarter against the quarter before (last_quarter_change).
    frozen_flat: float = float("nan")
    twin: LiveSplit | None = None

    @property
    def relative(self) -> float:
        return self.diff / self.frozen_mse if self.frozen_mse else float("nan")

    @property
    def flattened(self) -> bool:
        return bool(np.isfinite(self.frozen_flat) and self.frozen_flat >= -FLAT_TOLERANCE)

    @property
    def verdict(self) -> str:
        if len(self.seeds) >= 2 and not self.flattened:
            return NOT_FLAT
        return _verdict(self.seeds, self.diff_ci, HELPS, HURTS)


@dataclass
class TunedRanking:
    """The encoders of one backbone x suite that have both, ordered best first frozen and tuned
    (mean normalised MSE over the paired seeds; ties by name)."""

    backbone: str
    suite: str
    steps: int
    frozen_order: list[str] = field(default_factory=list)
    tuned_order: list[str] = field(default_factory=list)

    @property
    def changed(self) -> bool:
        return self.frozen_order != self.tuned_order

    @property
    def leader_changed(self) -> bool:
        return bool(self.frozen_order) and self.frozen_order[0] != self.tuned_order[0]


def is_tuned(record) -> bool:
    kind = kind_of(record)
    return kind is not None and kind.tune_encoder


def is_twin(record) -> bool:
    kind = kind_of(record)
    return kind is not None and kind.live_encoder


def _step_seconds(record) -> float:
    steps = record.training.train_steps
    train = (record.run.timings_s or {}).get("train")
    return float(train) / steps if steps and train is not None else float("nan")


def _cells(found: dict) -> str:
    """'seeds [0, 1]' on release 0 alone, else the (release, seed) pairs."""
    if all(r == 0 for r, _ in found):
        return f"seeds {sorted(s for _, s in found)}"
    return f"(release, seed) {sorted(found)}"


def compare_tuned(records: Sequence, backbone: str, suite: str, encoder: str, steps: int, *,
                  n_resamples: int = DEFAULT_RESAMPLES,
                  random_seed: int = 0) -> TunedComparison | str:
    """Tuned vs frozen for one encoder at `steps` training steps, or a one-line reason why they
    cannot be compared."""
    here = [r for r in records if (r.backbone, r.suite, r.encoder) == (backbone, suite, encoder)
            and r.training.train_steps == steps]
    tuned = {(int(r.release), int(r.seed)): r
             for r in sorted(here, key=lambda r: r.cell_id) if is_tuned(r)}
    frozen = {(int(r.release), int(r.seed)): r for r in here if r.kind in (GRAFT, SHORT_GRAFT)}
    twins = {(int(r.release), int(r.seed)): r
             for r in sorted(here, key=lambda r: r.cell_id) if is_twin(r)}
    keys = sorted(set(tuned) & set(frozen))
    seeds = sorted({s for _, s in keys})
    if not keys:
        at = f" at {steps} steps" if steps else ""
        return (f"{encoder}{at}: no seed with both a tuned cell and a frozen graft of as many "
                f"steps (tuned {_cells(tuned)}, frozen {_cells(frozen)})")
    try:  # row 0 frozen, row 1 tuned
        boot = paired_records_bootstrap([(frozen[k], tuned[k]) for k in keys],
                                        n_resamples=n_resamples, random_seed=random_seed)
    except WindowMismatchError as err:
        return f"{encoder}: not compared: {err}"
    split = live_split([(frozen[k], twins[k], tuned[k]) for k in keys if k in twins],
                       n_resamples=n_resamples, random_seed=random_seed)
    return TunedComparison(
        backbone, suite, encoder, steps, seeds, frozen_mse=float(boot.mean[0]),
        tuned_mse=float(boot.mean[1]), diff=float(boot.diff[1]),
        diff_ci=(float(boot.diff_lo[1]), float(boot.diff_hi[1])),
        tuned_step_s=float(np.mean([_step_seconds(tuned[k]) for k in keys])),
        frozen_step_s=float(np.mean([_step_seconds(frozen[k]) for k in keys])),
        frozen_flat=last_quarter_change([frozen[k].training.loss_curve for k in keys]),
        twin=split)


def live_split(triples: Sequence[tuple], *, n_resamples: int = DEFAULT_RESAMPLES,
               random_seed: int = 0) -> LiveSplit | None:
    """(frozen, twin, tuned) record triples, one per (release, seed) cell -> the split of tuned -
    frozen, both halves drawn by the same replicates (None without a triple, or when their
    windows differ)."""
    if not triples:
        return None
    try:
        vs_frozen = paired_records_bootstrap(triples, leader=0, n_resamples=n_resamples,
                                             random_seed=random_seed)
        vs_twin = paired_records_bootstrap(triples, leader=1, n_resamples=n_resamples,
                                           random_seed=random_seed)
    except WindowMismatchError:
        return None
    return LiveSplit(
        sorted({int(t[0].seed) for t in triples}), float(vs_frozen.mean[0]),
        float(vs_frozen.mean[1]), float(vs_frozen.mean[2]),
        path=float(vs_frozen.diff[1]),
        path_ci=(float(vs_frozen.diff_lo[1]), float(vs_frozen.diff_hi[1])),
        moved=float(vs_twin.diff[2]),
        moved_ci=(float(vs_twin.diff_lo[2]), float(vs_twin.diff_hi[2])),
        twin_step_s=float(np.mean([_step_seconds(t[1]) for t in triples])))


def tuned_ranking(comparisons: Sequence[TunedComparison]) -> TunedRanking:
    """Frozen and tuned orders of one backbone x suite's encoders compared at one step count."""
    first = comparisons[0]
    out = TunedRanking(first.backbone, first.suite, first.steps)
    out.frozen_order = [c.encoder for c in sorted(comparisons,
                                                  key=lambda c: (c.frozen_mse, c.encoder))]
    out.tuned_order = [c.encoder for c in sorted(comparisons,
                                                 key=lambda c: (c.tuned_mse, c.encoder))]
    return out


@dataclass
class TunedStudy:
    comparisons: list[TunedComparison] = field(default_factory=list)
    rankings: list[TunedRanking] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def tuned_vs_frozen(records: Sequence, *, n_resamples: int = DEFAULT_RESAMPLES,
                    random_seed: int = 0) -> TunedStudy:
    """Every encoder with tuned cells, per backbone x suite (the rankings' order) and step count
    (a full-length and a 1/8 tuned cell are two questions), and the orders of each; empty when
    no record is of a tuned kind."""
    study = TunedStudy()
    keys = sorted({(r.backbone, r.suite, r.training.train_steps, r.encoder)
                   for r in records if is_tuned(r)})
    order = backbone_order([b for b, _, _, _ in keys])
    for backbone, suite, steps in sorted({k[:3] for k in keys},
                                         key=lambda p: (p[1], order.index(p[0]), -(p[2] or 0))):
        found = []
        for encoder in sorted(e for b, s, n, e in keys if (b, s, n) == (backbone, suite, steps)):
            got = compare_tuned(records, backbone, suite, encoder, steps,
                                n_resamples=n_resamples, random_seed=random_seed)
            if isinstance(got, str):
                study.notes.append(f"{backbone} x {suite}: {got}")
            else:
                found.append(got)
        study.comparisons += found
        if found:
            study.rankings.append(tuned_ranking(found))
    return study
