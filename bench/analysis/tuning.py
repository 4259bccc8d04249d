"""Tuned encoder against frozen: does training the encoder's weights beside the projector beat
grafting it frozen, per encoder and backbone x suite, and does the encoder ranking change?

A tuned cell is any kind of the table with `tune_encoder` (bench.grid.kinds); its frozen twin is
the cell of the same backbone, suite, encoder and seed that trained the projector alone for the
same number of steps: the graft for a full-length tuned cell, the short_1_8 graft for
tuned_encoder_1_8 (both schedules compressed alike). diff = tuned - frozen on normalised
MSE (negative: tuning helps), averaged over the (release, seed) cells both have, with the
rankings' paired hierarchical bootstrap (releases, seeds, held-out episodes, windows:
bench.analysis.hierarchy). A verdict needs at least two seeds: one seed's difference is one
training's, and training noise moves grafts more than many of the gaps (docs/INTERVALS.md).
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

    @property
    def relative(self) -> float:
        return self.diff / self.frozen_mse if self.frozen_mse else float("nan")

    @property
    def verdict(self) -> str:
        if len(self.seeds) < 2:
            return ONE_SEED
        lo, hi = self.diff_ci
        if np.isfinite(hi) and hi < 0:
            return HELPS
        if np.isfinite(lo) and lo > 0:
            return HURTS
        return UNCLEAR


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
    return TunedComparison(
        backbone, suite, encoder, steps, seeds, frozen_mse=float(boot.mean[0]),
        tuned_mse=float(boot.mean[1]), diff=float(boot.diff[1]),
        diff_ci=(float(boot.diff_lo[1]), float(boot.diff_hi[1])),
        tuned_step_s=float(np.mean([_step_seconds(tuned[k]) for k in keys])),
        frozen_step_s=float(np.mean([_step_seconds(frozen[k]) for k in keys])))


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
