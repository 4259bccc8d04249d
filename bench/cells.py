"""Cells of the grid: what one pytest case measures, and its id."""

from __future__ import annotations

from dataclasses import dataclass

from bench.protocol import Profile

GRAFT = "graft"
NATIVE = "native"
NATIVE_WRAPPED = "native_wrapped"
LORA = "lora"
POOLING = "pooling"
ZERO_IMAGE = "zero_image"
SHUFFLED_IMAGE = "shuffled_image"
CONTROL_KINDS = (NATIVE, NATIVE_WRAPPED, LORA, POOLING, ZERO_IMAGE, SHUFFLED_IMAGE)
KINDS = (GRAFT,) + CONTROL_KINDS

# Pooling variants, relative to the backbone's native grid side.
POOL_VARIANTS = ("half", "double", "global")
# zero_image: "eval" zeroes images at evaluation only; "train" also trains on zeroed images.
ZERO_VARIANTS = ("eval", "train")


@dataclass(frozen=True)
class CellSpec:
    kind: str
    backbone: str
    suite: str
    seed: int
    encoder: str | None = None  # None for native and native_wrapped
    variant: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown cell kind {self.kind!r}; valid kinds: {', '.join(KINDS)}")
        # Only native-policy cells (and the native policy's image controls) run without an encoder.
        encoderless = (NATIVE, NATIVE_WRAPPED, ZERO_IMAGE, SHUFFLED_IMAGE)
        if self.encoder is None and self.kind not in encoderless:
            raise ValueError(f"cell kind {self.kind!r} needs an encoder")
        if self.encoder is None and self.kind == ZERO_IMAGE and self.variant != "eval":
            raise ValueError("the native policy is not retrained: zero_image needs variant 'eval'")
        if self.kind == POOLING and self.variant not in POOL_VARIANTS:
            raise ValueError(f"pooling variant {self.variant!r} not in {POOL_VARIANTS}")
        if self.kind == ZERO_IMAGE and self.variant not in ZERO_VARIANTS:
            raise ValueError(f"zero_image variant {self.variant!r} not in {ZERO_VARIANTS}")

    @property
    def trains_projector(self) -> bool:
        return self.kind != NATIVE and not (
            self.encoder is None and self.kind in (ZERO_IMAGE, SHUFFLED_IMAGE)
        )

    @property
    def id(self) -> str:
        """Reads as the cell: smolvla-spatial-dinov2_s-seed0, smolvla-spatial-native-seed0,
        smolvla-spatial-pixels-pool_half-seed0, smolvla-spatial-native-zero_image_eval-seed0."""
        parts = [self.backbone, self.suite]
        if self.kind in (NATIVE, NATIVE_WRAPPED):
            parts.append(self.kind)
        else:
            parts.append((self.encoder or NATIVE).replace(":", "_").replace("/", "_"))
            if self.kind == POOLING:
                parts.append(f"pool_{self.variant}")
            elif self.kind == ZERO_IMAGE:
                parts.append(f"zero_image_{self.variant}")
            elif self.kind != GRAFT:
                parts.append(self.kind)
        parts.append(f"seed{self.seed}")
        return "-".join(parts)

    @property
    def reference(self) -> "CellSpec | None":
        """The cell a control is compared against (its delta's denominator)."""
        if self.kind == NATIVE_WRAPPED:
            return CellSpec(NATIVE, self.backbone, self.suite, self.seed)
        if self.kind in (LORA, POOLING, ZERO_IMAGE, SHUFFLED_IMAGE):
            if self.encoder is None:
                return CellSpec(NATIVE, self.backbone, self.suite, self.seed)
            return CellSpec(GRAFT, self.backbone, self.suite, self.seed, self.encoder)
        return None


def graft_cells(profile: Profile) -> list[CellSpec]:
    return [
        CellSpec(GRAFT, b, s, seed, e)
        for b in profile.backbones
        for s in profile.suites
        for e in profile.encoders
        for seed in profile.seeds
    ]


def control_cells(profile: Profile) -> list[CellSpec]:
    cells: list[CellSpec] = []
    for b in profile.backbones:
        for s in profile.suites:
            for seed in profile.seeds:
                if NATIVE in profile.controls:
                    cells.append(CellSpec(NATIVE, b, s, seed))
                if NATIVE_WRAPPED in profile.controls:
                    cells.append(CellSpec(NATIVE_WRAPPED, b, s, seed))
                if ZERO_IMAGE in profile.controls:
                    cells.append(CellSpec(ZERO_IMAGE, b, s, seed, None, "eval"))
                if SHUFFLED_IMAGE in profile.controls:
                    cells.append(CellSpec(SHUFFLED_IMAGE, b, s, seed))
                for e in profile.control_encoders:
                    if LORA in profile.controls:
                        cells.append(CellSpec(LORA, b, s, seed, e))
                    if POOLING in profile.controls:
                        cells += [CellSpec(POOLING, b, s, seed, e, v) for v in POOL_VARIANTS]
                    if ZERO_IMAGE in profile.controls:
                        cells += [CellSpec(ZERO_IMAGE, b, s, seed, e, v) for v in ZERO_VARIANTS]
                    if SHUFFLED_IMAGE in profile.controls:
                        cells.append(CellSpec(SHUFFLED_IMAGE, b, s, seed, e))
    return cells
