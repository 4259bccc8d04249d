"""The published study's settings as a frozen table, and how a record's protocol compares.

Source: Zeng & She, "Encoder Winners Do Not Reliably Transfer Across VLA Backbone Scale"
(arXiv 2606.14153), as given by SECONDARY summaries of the paper: verify against the paper
before citing. Each constant maps to a `bench.grid.protocol.Protocol` field where one exists;
the others are compared with what the records carry (device, pooling grid, windows, seeds,
checkpoint) or with facts of our code stated in OUR_CODE (each guarded by a test).

`compare_protocol` works from a record's protocol DICT, whatever values it holds, so it stays true
while the profiles change. Every Protocol field the study does not set is listed as ours.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

from backbones import BACKBONES, study_backbone

if TYPE_CHECKING:  # this table stays light: no record code at import
    from bench.results.record import Record

STUDY_SOURCE = ("Zeng & She, arXiv 2606.14153, via secondary summaries of the paper: verify "
                "against the paper")

# Row statuses.
STUDY = "study"  # ours equals the study's value
OURS = "ours (study silent)"  # a constant of ours the study does not give
DISAGREES = "DISAGREES"
NOT_RECORDED = "not recorded"  # the study gives it; the records do not say what we used

# Facts of our code that no record carries (tests/test_study.py checks each against the code).
OUR_CODE = {
    "optimiser": "AdamW",  # bench/loops/train.py: torch.optim.AdamW
    "gradient accumulation": False,  # bench/loops/train.py: one optimiser step per batch
    # encoders/timm_encoders.py: one bilinear resize to the encoder's own input size, then its
    # own mean/std. The paper encoders' sizes: the study's one 224 px path (timm's pretrained
    # size, except fastvit_sa12's, 256):
    "input sizes": {"siglip": 224, "dinov2_s": 224, "fastvit": 224, "repvit": 224},
}


def _close(study: Any, ours: Any) -> bool:
    if isinstance(study, (int, float)) and isinstance(ours, (int, float)):
        return math.isclose(float(study), float(ours), rel_tol=1e-9, abs_tol=0.0)
    return str(study).strip().lower() == str(ours).strip().lower()


def _windows_agree(study: int, ours: Mapping[str, int]) -> bool:
    """The summaries do not say per suite or in total: either counts as agreement.

    `ours` is keyed by suite, or by "backbone x suite" where backbones differ (totals per
    backbone then)."""
    totals: dict[str, int] = {}
    for key, n in ours.items():
        backbone = key.split(" x ")[0] if " x " in key else ""
        totals[backbone] = totals.get(backbone, 0) + n
    return study in ours.values() or study in totals.values()


def _every_encoder_at(study: int, ours: Any) -> bool:
    return isinstance(ours, Mapping) and all(size == study for size in ours.values())


def _per_backbone_agree(study: Mapping[str, Any], ours: Mapping[str, Any]) -> bool:
    """Every backbone of ours matches the study's value for its family (none known: False)."""
    families = {b: study_backbone(b) for b in ours}
    return (bool(ours) and all(f in study for f in families.values())
            and all(_close(study[families[b]], v) for b, v in ours.items()))


def _seed_counts_agree(study: range, ours: Mapping[str, int]) -> bool:
    return all(n in study for n in ours.values())


@dataclass(frozen=True)
class StudyConstant:
    """One setting of the study: its value, the Protocol field it maps to (or None), a note."""

    name: str
    study: Any
    field: str | None
    note: str
    agrees: Callable[[Any, Any], bool] = _close


STUDY_CONSTANTS: tuple[StudyConstant, ...] = (
    StudyConstant("projector steps", 2000, "steps", "per run"),
    StudyConstant("optimiser", "AdamW", None, "ours: bench/loops/train.py, not a Protocol field"),
    StudyConstant("learning rate", 1e-4, "lr", "schedule not given by the summaries"),
    StudyConstant("effective batch", 8, "batch_size",
                  "we accumulate no gradients: batch_size is the effective batch"),
    StudyConstant("precision", "bf16", None,
                  "ours: bf16 autocast on CUDA, fp32 on CPU (bench/loops/train.py); from the "
                  "records' device"),
    StudyConstant("preprocessing: input px", 224, None,
                  "the study: one 224 px path for every encoder; ours: each encoder resized to "
                  "its own timm input size, then its own mean/std (the summaries do not say "
                  "whether one mean/std is shared)", _every_encoder_at),
    # Published per study backbone (keys: the registry's study entries, tests check it).
    StudyConstant("pooling grid", {"smolvla": "8x8", "pi05": "16x16"}, None,
                  "the backbone's native token grid per camera; ours from graft records' grid",
                  _per_backbone_agree),
    StudyConstant("held-out windows", 6457, None,
                  "summaries do not say per suite or in total; ours per suite (records' "
                  "n_windows)", _windows_agree),
    StudyConstant("seeds", range(2, 4), None, "seeds per backbone x suite; ours from graft records",
                  _seed_counts_agree),
    # The study's BASE releases are the registry's study entries (backbones/__init__.py).
    StudyConstant("checkpoints", {e.name: e.repo_id for e in BACKBONES.values() if e.study},
                  None, "the BASE releases; ours from the records' checkpoint field (or the "
                  "profile)",
                  _per_backbone_agree),
)
MAPPED_FIELDS = {c.field for c in STUDY_CONSTANTS if c.field}


@dataclass(frozen=True)
class ConstantRow:
    """One line of the comparison table; values already rendered as text."""

    constant: str
    study: str
    ours: str
    status: str  # STUDY | OURS | DISAGREES | NOT_RECORDED
    field: str | None
    note: str


def as_text(value: Any) -> str:
    """A table cell: 1e-4 -> '0.0001', {'pi05': '16x16'} -> 'pi05: 16x16', range(2, 4) -> '2-3'."""
    if value is None:
        return "not recorded"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, Mapping):
        return ", ".join(f"{k}: {as_text(v)}" for k, v in value.items())
    if isinstance(value, range):
        return f"{value.start}-{value.stop - 1}"
    if isinstance(value, (list, tuple)):
        return ", ".join(as_text(v) for v in value)
    return str(value)


def compare_protocol(protocol: Mapping[str, Any],
                     observed: Mapping[str, Any] | None = None) -> list[ConstantRow]:
    """Study table against one record's protocol dict (+ `observed` values by constant name).

    A study constant with a Protocol field reads it from `protocol`; the others read `observed`
    (see `observed_from_records`) and are NOT_RECORDED without it. Every other key of `protocol`
    follows as an OURS row."""
    observed = observed or {}
    rows = []
    for c in STUDY_CONSTANTS:
        ours = protocol.get(c.field) if c.field else observed.get(c.name)
        if ours is None:
            status = NOT_RECORDED
        else:
            status = STUDY if c.agrees(c.study, ours) else DISAGREES
        rows.append(ConstantRow(c.name, as_text(c.study), as_text(ours), status, c.field, c.note))
    for key, value in protocol.items():
        if key not in MAPPED_FIELDS:
            rows.append(ConstantRow(key, "not given", as_text(value), OURS, key,
                                    "Protocol field"))
    return rows


def _grid_text(grid: Any) -> str:
    return "x".join(str(int(g)) for g in grid) if isinstance(grid, (list, tuple)) else str(grid)


def observed_from_records(records: Sequence[Record]) -> dict[str, Any]:
    """What the records say we used, by study-constant name (absent where they do not say)."""
    from bench.grid.protocol import PROFILES  # plain dataclasses: no model, no runner

    out: dict[str, Any] = {"optimiser": OUR_CODE["optimiser"]}
    from bench.grid.kinds import GRAFT

    grafts = [r for r in records if r.kind == GRAFT]
    devices = {str(r.run.device) for r in records if r.run.device}
    on_cuda = {d.startswith("cuda") for d in devices}
    if on_cuda:
        out["precision"] = {frozenset({True}): "bf16", frozenset({False}): "fp32 (cpu)"}.get(
            frozenset(on_cuda), "mixed: bf16 on cuda, fp32 on cpu")
    profiles = {r.measured.profile for r in records} - {None}
    sources = {PROFILES[p].source if p in PROFILES else None for p in profiles}
    encoders = sorted({r.encoder for r in grafts})
    sizes = OUR_CODE["input sizes"]
    recorded = {r.encoder: r.training.encoder_input_size for r in grafts
                if r.training.encoder_input_size}
    if encoders and all(e in recorded for e in encoders):  # each encoder's own, as it ran
        out["preprocessing: input px"] = {e: recorded[e] for e in encoders}
    elif sources == {"hub"} and encoders and all(e in sizes for e in encoders):
        out["preprocessing: input px"] = {e: sizes[e] for e in encoders}
    # Tiny records from before encoder_input_size: not recorded. A guess ("56-64 px") was false
    # for the encoders that keep their own size in every profile (encoders/real.py: 224 px).
    grids: dict[str, set[str]] = {}
    for r in grafts:
        if r.measured.grid is not None:
            grids.setdefault(r.backbone, set()).add(_grid_text(r.measured.grid))
    if grids:
        out["pooling grid"] = {b: " / ".join(sorted(g)) for b, g in sorted(grids.items())}
    windows = {(r.backbone, r.suite): int(r.scores.n_windows) for r in grafts}
    per_suite: dict[str, set[int]] = {}
    for (_, suite), n in windows.items():
        per_suite.setdefault(suite, set()).add(n)
    if all(len(v) == 1 for v in per_suite.values()):
        out["held-out windows"] = {s: min(v) for s, v in sorted(per_suite.items())} or None
    else:
        out["held-out windows"] = {f"{b} x {s}": n for (b, s), n in sorted(windows.items())}
    seeds: dict[str, set[int]] = {}
    for r in grafts:
        seeds.setdefault(f"{r.backbone} x {r.suite}", set()).add(int(r.seed))
    if seeds:
        out["seeds"] = {k: len(v) for k, v in sorted(seeds.items())}
    checkpoints: dict[str, set[str]] = {}
    for r in records:
        checkpoint = _repo_id(r.measured.checkpoint)
        if checkpoint:
            checkpoints.setdefault(r.backbone, set()).add(str(checkpoint))
    if checkpoints:
        out["checkpoints"] = {b: " / ".join(sorted(c)) for b, c in sorted(checkpoints.items())}
    elif sources == {"tiny"}:
        out["checkpoints"] = {b: "tiny policy built locally"
                              for b in sorted({r.backbone for r in records})}
    return out


def _repo_id(checkpoint: Any) -> str | None:
    """A record's checkpoint: {"repo_id": ..., "revision": ...}, or a bare repo id (older)."""
    return checkpoint.get("repo_id") if isinstance(checkpoint, Mapping) else checkpoint


def compare_records(records: Sequence[Record]) -> dict[str, list[ConstantRow]]:
    """{protocol_hash: rows} over the records of each protocol."""
    groups: dict[str, list[Record]] = {}
    for r in records:
        groups.setdefault(str(r.measured.protocol_hash or "?"), []).append(r)
    return {h: compare_protocol(recs[0].measured.protocol or {}, observed_from_records(recs))
            for h, recs in groups.items()}
