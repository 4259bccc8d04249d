"""The fixed wrapper: pooled feature grid -> LayerNorm (no affine) -> ONE trainable Linear.

Pooling to the token grid happens before this module (bench.run.features.pool_grid), so the cache can
hold pooled features; `GraftFeed` is what replaces the backbone's pixels -> LM-embedding step.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor, nn

from bench.run.features import pool_grid


class Projector(nn.Module):
    """(B, N, C_enc) pooled features -> (B, N, D_lm). Only `linear` has parameters."""

    def __init__(self, enc_channels: int, lm_width: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(enc_channels, elementwise_affine=False)
        self.linear = nn.Linear(enc_channels, lm_width)

    def forward(self, pooled: Tensor) -> Tensor:
        return self.linear(self.norm(pooled))


class GraftFeed:
    """Stands in for `embed_image`: each call (one per camera, in camera order) returns the
    projected features bound for this batch.

    Two sources, same numbers: `bind(features)` with pooled features computed outside (cache or
    encoder in the loop, from the dataset's own pixels), or `tower` (a function of the image the
    policy hands its vision tower, returning a (B, C, h, w) grid) for the native_wrapped control.
    """

    def __init__(
        self,
        projector: Projector,
        camera_keys: tuple[str, ...],
        grid: tuple[int, int],
        tower: Callable[[Tensor], Tensor] | None = None,
    ) -> None:
        self.projector = projector
        self.camera_keys = camera_keys
        self.grid = grid
        self.tower = tower
        self._pending: list[Tensor] = []

    def bind(self, features: dict[str, Tensor]) -> None:
        missing = [k for k in self.camera_keys if k not in features]
        if missing:
            raise KeyError(f"graft features missing cameras {missing}; have {sorted(features)}")
        self._pending = [features[k] for k in self.camera_keys]

    def assert_consumed(self) -> None:
        if self._pending:
            raise RuntimeError(
                f"the backbone consumed only {len(self.camera_keys) - len(self._pending)} of "
                f"{len(self.camera_keys)} cameras: its camera list differs from the suite's"
            )

    def __call__(self, image: Tensor) -> Tensor:
        if self.tower is not None:
            with torch.no_grad():
                pooled = pool_grid(self.tower(image).float(), self.grid)
        else:
            if not self._pending:
                raise RuntimeError(
                    "the backbone asked for more camera embeddings than the suite has cameras "
                    f"({self.camera_keys}); check the policy's image features / empty_cameras"
                )
            pooled = self._pending.pop(0)
        if pooled.shape[0] != image.shape[0]:
            raise RuntimeError(f"graft batch {pooled.shape[0]} != image batch {image.shape[0]}")
        return self.projector(pooled.to(image.device))


def trainable_parameters(*modules: nn.Module) -> int:
    """Number of parameters with requires_grad over the given modules (shared ones once)."""
    seen: set[int] = set()
    total = 0
    for module in modules:
        for p in module.parameters():
            if p.requires_grad and id(p) not in seen:
                seen.add(id(p))
                total += p.numel()
    return total


def assert_only_trainable(expected: int, *modules: nn.Module, what: str = "projector") -> None:
    """Freeze check of every cell: the trainable count must equal the projector's (+ LoRA)."""
    found = trainable_parameters(*modules)
    if found != expected:
        names = [
            n for m in modules for n, p in m.named_parameters() if p.requires_grad
        ][:8]
        raise AssertionError(
            f"freeze violated: {found} trainable parameters, expected {expected} ({what}); "
            f"first trainable: {names}"
        )
