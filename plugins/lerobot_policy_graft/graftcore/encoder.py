"""The graft's encoder: a frozen timm model, camera pixels in [0, 1] -> a (B, C, h, w) grid.

graftbench's encoder registry (encoders.timm_encoders) builds its timm encoders as this class, and
an export rebuilds the same one from its config (`encoder_from_config`), so a graft loads where
graftbench is not installed. No timm import at module level: LeRobot's CLIs import the plugin at
start, and timm is only needed once a grafted policy is built.
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class GridSpec(Protocol):
    """What TimmEncoder reads of its spec (graftbench's encoders.base.EncoderSpec has it all)."""

    name: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    num_prefix_tokens: int  # cls/register tokens dropped before the grid is formed
    layout: str  # "tokens" (ViT: (B, N, C)) or "map" (CNN: (B, C, h, w))


class CheckpointSpec(NamedTuple):
    """An exported graft's encoder as its config describes it (a GridSpec)."""

    name: str
    timm_name: str
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    num_prefix_tokens: int
    layout: str


def resized_normalised(images: Tensor, input_size: int, mean: Tensor, std: Tensor) -> Tensor:
    """(B, 3, H, W) in [0,1] -> (B, 3, S, S) in mean's dtype: bilinear antialiased resize to
    S = input_size (skipped at that size), then (x - mean) / std; mean, std (1, 3, 1, 1)."""
    x = images.to(mean.dtype)
    if tuple(x.shape[-2:]) != (input_size, input_size):
        x = F.interpolate(x, size=(input_size, input_size), mode="bilinear",
                          antialias=True, align_corners=False)
    return (x - mean) / std


class FrozenEncoder(nn.Module):
    """A frozen, eval-mode image encoder fed camera pixels in [0, 1], resized to `input_size` and
    normalised by its spec's mean/std (`normalised`). Subclasses set their modules, then call
    `freeze()`: TimmEncoder here, graftbench's ModuleEncoder (encoders.user_encoders)."""

    def __init__(self, spec: GridSpec, input_size: int, weights_id: str) -> None:
        super().__init__()
        self.spec = spec
        self.input_size = input_size
        self.weights_id = weights_id
        self.register_buffer("mean", torch.tensor(spec.mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(spec.std).view(1, 3, 1, 1), persistent=False)

    def freeze(self) -> None:
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "FrozenEncoder":
        # Frozen means frozen: a parent's .train() must not switch BatchNorm/dropout back on.
        return super().train(False)

    def normalised(self, images: Tensor) -> Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, 3, S, S) as the encoder takes them (S = input_size)."""
        return resized_normalised(images, self.input_size, self.mean, self.std)


class TimmEncoder(FrozenEncoder):
    """A frozen timm model. forward: (B, 3, H, W) float in [0,1] -> (B, C, h, w) float32."""

    def __init__(self, spec: GridSpec, model: nn.Module, input_size: int, weights_id: str):
        super().__init__(spec, input_size, weights_id)
        self.model = model
        # What timm.create_model received besides num_classes=0 (set by graftbench's
        # build_timm_encoder): with the timm name it rebuilds this architecture (an export).
        self.timm_kwargs: dict = {}
        self.channels = int(model.num_features)
        self.output_fmt = str(getattr(model, "output_fmt", "NCHW"))
        self.freeze()

    @torch.no_grad()
    def forward(self, images: Tensor) -> Tensor:
        return self.grid(images)

    def grid(self, images: Tensor) -> Tensor:
        """forward with autograd on: for a graft that trains its encoder (train_scope)."""
        feats = self.model.forward_features(self.normalised(images))
        if self.spec.layout == "tokens":
            return tokens_to_grid(feats, self.spec.num_prefix_tokens).float()
        if self.output_fmt == "NHWC":
            feats = feats.permute(0, 3, 1, 2)
        return feats.float().contiguous()


def tokens_to_grid(tokens: Tensor, num_prefix_tokens: int) -> Tensor:
    """(B, P + h*w, C) tokens -> (B, C, h, w), dropping the P prefix (cls/register) tokens."""
    patches = tokens[:, num_prefix_tokens:]
    b, n, c = patches.shape
    side = math.isqrt(n)
    if side * side != n:
        raise ValueError(f"{n} patch tokens (after dropping {num_prefix_tokens} prefix tokens) do "
                         f"not form a square grid; check num_prefix_tokens of the encoder spec")
    return patches.transpose(1, 2).reshape(b, c, side, side)


def encoder_from_config(config) -> TimmEncoder:
    """A graft config's timm architecture, random init (the checkpoint holds its weights):
    (B, 3, H, W) in [0, 1] -> (B, C, h, w) float32. `config`: configuration_graft.GraftFields."""
    import timm

    spec = CheckpointSpec(name=config.encoder_name or f"timm:{config.encoder_timm_name}",
                          timm_name=config.encoder_timm_name, mean=tuple(config.encoder_mean),
                          std=tuple(config.encoder_std),
                          num_prefix_tokens=config.encoder_num_prefix_tokens,
                          layout=config.encoder_layout)
    kwargs = config.timm_kwargs
    model = timm.create_model(config.encoder_timm_name, pretrained=False, num_classes=0, **kwargs)
    encoder = TimmEncoder(spec, model, config.encoder_input_size, weights_id="checkpoint")
    encoder.timm_kwargs = kwargs
    if encoder.channels != config.encoder_channels:
        raise ValueError(f"{config.encoder_timm_name} with {config.encoder_timm_kwargs} has "
                         f"{encoder.channels} channels, the config says {config.encoder_channels}")
    return encoder
