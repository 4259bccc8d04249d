"""The fixed wrapper of a graft: encoder grid -> adaptive average pooling to the backbone's token
grid (`pool_grid`) -> LayerNorm without affine parameters -> ONE Linear (`Projector`).

`GraftFeed` is what stands in for a policy's pixels -> LM-embedding step. It lives in the plugin,
which must load an export where graftbench is not installed; graftbench's harness (bench.run)
imports it from here, so an export runs the very code the harness measured with.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def pool_grid(grid: Tensor, target: tuple[int, int]) -> Tensor:
    """(B, C, h, w) -> (B, rows*cols, C) by adaptive average pooling; tokens in row-major order."""
    rows, cols = target
    pooled = F.adaptive_avg_pool2d(grid, (rows, cols))  # (B, C, rows, cols)
    return pooled.flatten(2).transpose(1, 2)


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
