"""What a candidate encoder is to the harness: frozen pixels -> 2-D feature grid."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from graftcore.encoder import resized_normalised  # noqa: F401  (the plugin's, one copy)
from torch import Tensor


class UnknownEncoder(ValueError):
    pass


@dataclass(frozen=True)
class EncoderSpec:
    """One registry entry. Architecture arguments stay apart from the pretrained config (timm)."""

    name: str  # registry name, e.g. "dinov2_s"; "timm:<model>" entries are made on the fly
    timm_name: str | None  # e.g. "vit_small_patch14_dinov2"; None for the known-answer encoders
    input_size: int  # square input side the encoder is fed (pixels)
    mean: tuple[float, float, float] = (0.5, 0.5, 0.5)
    std: tuple[float, float, float] = (0.5, 0.5, 0.5)
    num_prefix_tokens: int = 0  # cls/register tokens dropped before the grid is formed
    layout: str = "tokens"  # "tokens" (ViT: (B, N, C)) or "map" (CNN: (B, C, h, w))
    # Tiny profile: the SAME timm architecture with these constructor overrides, random init.
    tiny_kwargs: dict = field(default_factory=dict, hash=False, compare=False)
    tiny_input_size: int | None = None
    description: str = ""


class Encoder(torch.nn.Module):
    """Frozen, eval-mode encoder. forward: (B, 3, H, W) float in [0,1] -> (B, C, h, w) float32."""

    spec: EncoderSpec
    channels: int
    weights_id: str  # identifies the weights for the feature cache key (e.g. "pretrained", "init-seed0")

    def forward(self, images: Tensor) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError
