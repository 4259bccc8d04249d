"""Known-answer encoders for validity tests: `pixels` keeps all visual information, `blind` none.

Both take images at their native size (no resize); `input_size` in their specs is nominal.

`pixels` subtracts each image's mean colour before patchifying. Raw pixels left the pooled,
LayerNormed grid dominated by the table colour every window shares, and 200 projector steps then
learned little beyond a constant (tiny pi0.5, slot world, spatial seed 0: pixels 1.7% better
than blind raw, 12.2% centred). Only the global mean colour is dropped (constant up to the objects
in the tiny world); everything else the image shows is kept exactly.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from encoders.base import Encoder, EncoderSpec
from encoders.registry import register

PIXEL_PATCH = 8
BLIND_SHAPE = (16, 2, 2)  # (C, h, w)


class _KnownEncoder(Encoder):
    """No weights: the same module whatever the source; always in eval mode like any encoder."""

    channels: int
    # No weights; names the definition, so the feature cache never mixes two definitions.
    weights_id = "none"

    def __init__(self, spec: EncoderSpec, source: str = "tiny"):
        super().__init__()
        self.spec = spec
        self.input_size = spec.input_size
        self.eval()

    def train(self, mode: bool = True) -> "_KnownEncoder":
        return super().train(False)


class PixelsEncoder(_KnownEncoder):
    """Mean-centred pixels, patchified: (B, 3, H, W) -> (B, 3*8*8, H/8, W/8), channel
    c*64 + dy*8 + dx = pixel minus the image's mean of colour c."""

    channels = 3 * PIXEL_PATCH * PIXEL_PATCH
    weights_id = "none:centred"

    def forward(self, images: Tensor) -> Tensor:
        b, c, h, w = images.shape
        if c != 3 or h % PIXEL_PATCH or w % PIXEL_PATCH:
            raise ValueError(f"pixels encoder needs (B, 3, H, W) with H, W multiples of "
                             f"{PIXEL_PATCH}; got {tuple(images.shape)}")
        images = images.float()
        centred = images - images.mean(dim=(2, 3), keepdim=True)
        patches = F.unfold(centred, kernel_size=PIXEL_PATCH, stride=PIXEL_PATCH)
        return patches.reshape(b, self.channels, h // PIXEL_PATCH, w // PIXEL_PATCH)


class BlindEncoder(_KnownEncoder):
    """Constant all-ones grid (B, 16, 2, 2) whatever the input: carries no visual information."""

    channels = BLIND_SHAPE[0]

    def forward(self, images: Tensor) -> Tensor:
        return torch.ones((images.shape[0], *BLIND_SHAPE), dtype=torch.float32,
                          device=images.device)


register(EncoderSpec(
    name="pixels", timm_name=None, input_size=64, layout="map",
    description="known answer: mean-centred 8x8 pixel patches, 192 ch, (H/8)x(W/8) grid; all "
                "visual information but the mean colour, no learning"), PixelsEncoder)

register(EncoderSpec(
    name="blind", timm_name=None, input_size=64, layout="map",
    description="known answer: constant ones, 16 ch, 2x2 grid; no visual information"),
    BlindEncoder)


# The known-answer ladder (issue 26): the pixels encoder on the image averaged over f x f blocks
# (repeated back to full size, so grid and channels stay the pixels encoder's). Each rung is a
# function of the rung above, so it cannot hold more about the scene; blind is the last rung.
# `pytest bench --screen --encoders <LADDER> --screen-keep all` checks a screen against it.
LADDER_FACTORS = (2, 4, 8, 16)
LADDER = ("pixels", *(f"pixels_avg{f}" for f in LADDER_FACTORS), "blind")


class CoarsePixelsEncoder(PixelsEncoder):
    """The pixels encoder on `factor` x `factor` block means of the image."""

    factor = 1

    def forward(self, images: Tensor) -> Tensor:
        h, w = images.shape[-2:]
        if h % self.factor or w % self.factor:
            raise ValueError(f"{self.spec.name} needs H, W multiples of {self.factor}; got "
                             f"{tuple(images.shape)}")
        coarse = F.avg_pool2d(images.float(), self.factor)
        full = coarse.repeat_interleave(self.factor, dim=2).repeat_interleave(self.factor, dim=3)
        return super().forward(full)


for _factor in LADDER_FACTORS:
    register(EncoderSpec(
        name=f"pixels_avg{_factor}", timm_name=None, input_size=64, layout="map",
        description=f"known-answer ladder: pixels of the image averaged over {_factor}x{_factor} "
                    "blocks; less visual information than the rung above"),
        type(f"CoarsePixels{_factor}", (CoarsePixelsEncoder,),
             # weights_id names the definition: the feature store keys on it
             {"factor": _factor, "weights_id": f"none:centred:avg{_factor}"}))
