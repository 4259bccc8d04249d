"""Control cells against their references: wrapper neutrality, every control's delta, vision use.

delta = (control - reference) / reference, on mean MSE over the held-out windows, normalised and
raw. The wrapper-neutrality delta is this delta for native_wrapped against native. `vision_check`
asks whether a backbone x suite's best graft beats its no-vision controls (VISION_RULE).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np

from bench.analysis.rankings import (
    DEFAULT_RESAMPLES, WindowMismatchError, backbone_order, graft_records,
    paired_records_bootstrap,
)
from bench.grid.kinds import CELL_KINDS, GRAFT, NATIVE, NATIVE_SLOT, ZERO, get_kind, is_native_like, kind_of
from bench.results.record import NORMALIZED, RAW

METRICS = (NORMALIZED, RAW)


def relative_delta(value: float, reference: float) -> float:
    """(value - reference) / reference; NaN when the reference is 0 or not finite."""
    if not np.isfinite(reference) or reference == 0:
        return float("nan")
    return float((value - reference) / reference)


def find_reference(record: dict, records: Sequence[dict]) -> tuple[dict | None, str]:
    """The record a control is compared against, and the id looked for.

    Uses `record.reference`; without one, the graft cell of the same encoder and seed, or for
    native_wrapped / native-image controls the native cell (same seed if there is one)."""
    by_id = {r.cell_id: r for r in records}
    wanted = record.reference
    if wanted:
        return by_id.get(wanted), wanted
    native_like = is_native_like(record)
    kind = NATIVE if native_like else GRAFT
    candidates = [r for r in records
                  if r.kind == kind and r.backbone == record.backbone
                  and r.suite == record.suite
                  and (native_like or r.encoder == record.encoder)]
    same_seed = [r for r in candidates if r.seed == record.seed]
    # The released policy does not depend on a cell seed: any seed's native cell will do.
    for r in same_seed or (candidates if native_like else []):
        return r, r.cell_id
    label = NATIVE if native_like else f"{record.encoder} graft"
    return None, f"({label}, seed {record.seed})"


@dataclass
class ControlDelta:
    cell_id: str
    kind: str
    backbone: str
    suite: str
    encoder: str | None
    variant: str | None
    seed: int
    reference_id: str
    reference_found: bool
    mse: dict[str, float]
    reference_mse: dict[str, float] = field(default_factory=dict)
    delta: dict[str, float] = field(default_factory=dict)
    release: int = 0

    @property
    def cell(self) -> int | str:
        """Its (release, seed) cell as per-cell tables key it: the seed on release 0."""
        return self.seed if not self.release else f"rel{self.release}-seed{self.seed}"

    @property
    def label(self) -> str:
        return get_kind(self.kind).label(self.encoder, self.variant)


def control_deltas(records: Sequence[dict]) -> list[ControlDelta]:
    """One ControlDelta per control record (native_wrapped, lora, pooling, zero/shuffled image)."""
    out = []
    for r in sorted(records, key=lambda r: (r.backbone, r.suite, r.kind, r.cell_id)):
        kind = kind_of(r)
        if kind is None or not kind.control or kind.tier:  # a tier: bench.analysis.tiers
            continue
        ref, ref_id = find_reference(r, records)
        cd = ControlDelta(cell_id=r.cell_id, kind=r.kind, backbone=r.backbone,
                          suite=r.suite, encoder=r.encoder, variant=r.variant,
                          seed=int(r.seed), release=int(r.release), reference_id=ref_id,
                          reference_found=ref is not None,
                          mse={m: float(r.mse_in(m)) for m in METRICS})
        if ref is not None:
            cd.reference_mse = {m: float(ref.mse_in(m)) for m in METRICS}
            cd.delta = {m: relative_delta(cd.mse[m], cd.reference_mse[m]) for m in METRICS}
        out.append(cd)
    return out


@dataclass
class WrapperNeutrality:
    """(native_wrapped - native) / native on one backbone x suite, per (release, seed) cell
    (`ControlDelta.cell`) and mean over them."""

    backbone: str
    suite: str
    per_seed: dict[int | str, dict[str, float]] = field(default_factory=dict)  # cell -> delta
    mean: dict[str, float] = field(default_factory=dict)
    unmatched: list[str] = field(default_factory=list)  # wrapped cells without a native record

    def to_dict(self) -> dict:
        return asdict(self)


def wrapper_neutrality(records: Sequence[dict]) -> dict[tuple[str, str], WrapperNeutrality]:
    """{(backbone, suite): WrapperNeutrality} from native_wrapped cells and their native refs."""
    out: dict[tuple[str, str], WrapperNeutrality] = {}
    for cd in control_deltas(records):
        if not get_kind(cd.kind).tower:
            continue
        wn = out.setdefault((cd.backbone, cd.suite), WrapperNeutrality(cd.backbone, cd.suite))
        if cd.reference_found:
            wn.per_seed[cd.cell] = dict(cd.delta)
        else:
            wn.unmatched.append(f"{cd.cell_id} (reference {cd.reference_id} missing)")
    for wn in out.values():
        if wn.per_seed:
            wn.mean = {m: float(np.mean([d[m] for d in wn.per_seed.values()])) for m in METRICS}
    return out


# ---------------------------------------------------------------------------------------------
# Does the best graft use vision? (else its backbone x suite ranking measures nothing)

BLIND = "blind"  # the encoder that sees nothing (encoders/known.py)
UNCHECKED_HINT = "vision use not checked: run the blind or zero_image control"
VISION_RULE = (
    "A backbone x suite's encoder ranking measures vision only if its best graft (lowest mean "
    "normalised MSE over seeds, `blind` excluded) is better than every blind or zero-image "
    "control present: the blind graft (same seeds), a zero_image control of the best encoder "
    "(each variant) or of the native policy. Better = the 95% interval of (control - best "
    "graft) lies above 0. Pooling over releases and seeds: per (release, seed) cell, the mean "
    "over identical held-out "
    "windows of the per-window difference; these are averaged over the seeds both cells have "
    "(a native-policy control does not depend on the seed: its cell is paired with every graft "
    "seed of its release); the interval is the rankings' paired hierarchical bootstrap "
    "(releases, seeds, held-out episodes, windows: bench/analysis/hierarchy.py)."
)


@dataclass
class VisionComparison:
    """Best graft against one no-vision control; `diff` is control minus graft, normalised MSE."""

    control: str  # "blind graft", "zero_image[train] of siglip", "zero_image[eval] of native"
    cell_ids: list[str]
    seeds: list[int]
    control_mse: float
    diff: float
    diff_ci: tuple[float, float]

    @property
    def better(self) -> bool:
        """True when the graft is better: the interval of (control - graft) lies above 0."""
        return bool(np.isfinite(self.diff_ci[0]) and self.diff_ci[0] > 0.0)


@dataclass
class VisionCheck:
    """Whether the best graft of one backbone x suite beats its no-vision controls."""

    backbone: str
    suite: str
    best_encoder: str | None = None
    best_mse: float = float("nan")
    comparisons: list[VisionComparison] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def checked(self) -> bool:
        return bool(self.comparisons)

    @property
    def flagged(self) -> bool:
        """The ranking says nothing: some control is not beaten by the best graft."""
        return any(not c.better for c in self.comparisons)

    @property
    def status(self) -> str:
        if not self.checked:
            return "unchecked"
        return "FLAGGED" if self.flagged else "uses vision"

    @property
    def failed_controls(self) -> list[str]:
        return [c.control for c in self.comparisons if not c.better]

    def to_dict(self) -> dict:
        out = asdict(self)
        out.update(status=self.status, flagged=self.flagged,
                   better={c.control: c.better for c in self.comparisons})
        return out


def _no_vision_controls(records: Sequence[dict], backbone: str, suite: str,
                        best: str) -> list[tuple[str, list[dict], bool]]:
    """(label, cells, seed_free) for every blind / zero-image control present, in that order."""
    here = [r for r in records if r.backbone == backbone and r.suite == suite]
    groups: list[tuple[str, list[dict], bool]] = []
    blind = [r for r in here if r.kind == GRAFT and r.encoder == BLIND]
    if blind:
        groups.append(("blind graft", blind, False))
    # Controls whose policy sees no image at evaluation, in table order (zero_image).
    for kind in (k for k in CELL_KINDS.values() if k.control and k.eval_inputs == ZERO):
        mine_of = [r for r in here if r.kind == kind.name]
        for owner, seed_free in ((best, False), (NATIVE_SLOT, True)):
            mine = [r for r in mine_of if (r.encoder or NATIVE_SLOT) == owner]
            for variant in sorted({r.variant or "" for r in mine}):
                cells = [r for r in mine if (r.variant or "") == variant]
                label = kind.label(None if owner == NATIVE_SLOT else owner, variant or None)
                groups.append((label, cells, seed_free))
    return groups


def vision_check(records: Sequence[dict], backbone: str, suite: str, *,
                 n_resamples: int = DEFAULT_RESAMPLES, random_seed: int = 0) -> VisionCheck:
    """Best graft of `backbone` x `suite` against its blind / zero-image controls (VISION_RULE)."""
    check = VisionCheck(backbone=backbone, suite=suite)
    grafts = [r for r in graft_records(records, backbone, suite) if r.encoder != BLIND]
    if not grafts:
        check.notes.append("no graft cells besides blind")
        return check
    seed_means: dict[str, list[float]] = {}
    for r in grafts:
        seed_means.setdefault(r.encoder, []).append(
            float(np.mean(r.scores.per_window_in(NORMALIZED))))
    means = {e: float(np.mean(v)) for e, v in seed_means.items()}
    check.best_encoder = min(means, key=lambda e: (means[e], e))
    check.best_mse = means[check.best_encoder]
    best_cells = sorted((r for r in grafts if r.encoder == check.best_encoder),
                        key=lambda r: (int(r.release), int(r.seed)))
    for label, controls, seed_free in _no_vision_controls(records, backbone, suite,
                                                          check.best_encoder):
        by_cell = {(int(r.release), int(r.seed)): r
                   for r in sorted(controls, key=lambda r: r.cell_id)}
        by_release = {int(r.release): r for r in sorted(controls, key=lambda r: r.cell_id,
                                                        reverse=True)}
        # a seed-free control (the released policy's own) pairs with each seed of its release
        pairs = [(g, by_cell.get((int(g.release), int(g.seed)),
                                 by_release.get(int(g.release)) if seed_free else None))
                 for g in best_cells]
        pairs = [(g, c) for g, c in pairs if c is not None]
        if not pairs:
            check.notes.append(f"{label}: no seed in common with the {check.best_encoder} graft "
                               f"(control (release, seed) cells {sorted(by_cell)})")
            continue
        try:  # row 0 the best graft, row 1 the control
            boot = paired_records_bootstrap(pairs, n_resamples=n_resamples,
                                            random_seed=random_seed)
        except WindowMismatchError as err:
            check.notes.append(f"{label}: not compared: {err}")
            continue
        check.comparisons.append(VisionComparison(
            control=label, cell_ids=sorted({c.cell_id for _, c in pairs}),
            seeds=sorted({int(g.seed) for g, _ in pairs}), control_mse=float(boot.mean[1]),
            diff=float(boot.diff[1]), diff_ci=(float(boot.diff_lo[1]), float(boot.diff_hi[1]))))
    return check


def vision_checks(records: Sequence[dict], *, n_resamples: int = DEFAULT_RESAMPLES,
                  random_seed: int = 0) -> list[VisionCheck]:
    """One VisionCheck per backbone x suite with graft cells, in the rankings' order."""
    pairs = sorted({(r.backbone, r.suite) for r in records if r.kind == GRAFT})
    order = backbone_order([b for b, _ in pairs])
    return [vision_check(records, b, s, n_resamples=n_resamples, random_seed=random_seed)
            for b, s in sorted(pairs, key=lambda p: (p[1], order.index(p[0])))]
