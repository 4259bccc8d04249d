"""Images to pooled features: `encode_pooled` is the one function that turns a camera's images
into the pooled features a graft reads, in the loop (a tuned encoder, rollouts, perturbed
images) and, through `encode_grid`, into a feature store (bench.resources.features)."""

from __future__ import annotations

import torch
from torch import Tensor

from encoders.base import Encoder
from graftcore.graft import pool_grid


def encoder_device(encoder: Encoder) -> torch.device:
    """Device of the encoder's parameters or buffers (CPU for parameter-free encoders)."""
    for tensor in (*encoder.parameters(), *encoder.buffers()):
        return tensor.device
    return torch.device("cpu")


def encode_grid(encoder: Encoder, images_by_camera: dict[str, Tensor],
                grad: bool = False) -> dict[str, Tensor]:
    """{camera: (B, 3, H, W) in [0,1]} -> {camera: (B, C, h, w) float32}, the encoder's own grid.
    `grad`: through the encoder's autograd entry (`grid`: its forward is no_grad), for a cell
    that trains the encoder's weights (bench.grid.kinds tune_encoder); the same computation."""
    device = encoder_device(encoder)
    if grad:
        return {camera: encoder.grid(images.to(device, torch.float32)).float()
                for camera, images in images_by_camera.items()}
    with torch.no_grad():
        return {camera: encoder(images.to(device, torch.float32)).float()
                for camera, images in images_by_camera.items()}


def encode_pooled(encoder: Encoder, images_by_camera: dict[str, Tensor],
                  target_grid: tuple[int, int], grad: bool = False) -> dict[str, Tensor]:
    """{camera: (B, 3, H, W) in [0,1]} -> {camera: (B, rows*cols, C) float32} on the encoder's
    device (`grad`: as encode_grid's)."""
    return {camera: pool_grid(grid, target_grid).contiguous()
            for camera, grid in encode_grid(encoder, images_by_camera, grad).items()}
