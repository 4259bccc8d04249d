"""Known-answer encoders for validity tests: `pixels` keeps all visual information, `blind` none.

Both take images at their native size (no resize); `input_size` in their specs is nominal.

`pixels` subtracts each image's mean colour before patchifying. Raw pixels left the pooled,
LayerNormed grid dominated by the table colour every window shares, and 200 projector steps then
learned little beyond a constant (tiny pi0.5, slot world, spatial seed 0: pixels 1.7% better
than blind raw, 12.2% centred). Only the global mean colour is dropped (constant up to the objects
in the tiny world); everything else the image shows is kept exactly.
"""

from __future__ import annotations

import hashlib

import torch
import torch.nn.functional as F
from torch import Tensor

from encoders.base import Encoder, EncoderSpec, resized_normalised
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


def centred_patches(images: Tensor, patch: int) -> Tensor:
    """(B, 3, H, W) -> (B, 3*patch*patch, H/patch, W/patch): each image minus its mean colour,
    patchified; channel c*patch^2 + dy*patch + dx."""
    b, c, h, w = images.shape
    centred = images - images.mean(dim=(2, 3), keepdim=True)
    patches = F.unfold(centred, kernel_size=patch, stride=patch)
    return patches.reshape(b, c * patch * patch, h // patch, w // patch)


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
        return centred_patches(images.float(), PIXEL_PATCH)


class ConstantBlockPixelsEncoder(PixelsEncoder):
    """`pixels` beside a constant block: (B, 3, H, W) -> (B, 384, H/8, W/8), channels 0..191
    `pixels`' centred patches, 192..383 = `constant`.

    Why beside `pixels`: the wrapper's LayerNorm normalises each token over its channels, so a
    gain on every pixel (a dimmer scene) leaves `pixels`' tokens where they were (measured: its
    graft's MSE moved by < 0.3% at gain 0.4). The constant is not scaled with the pixels, so here
    the LayerNorm keeps how bright the scene is: a graft of this encoder sees a brightness
    change, as a real encoder would."""

    channels = 2 * 3 * PIXEL_PATCH * PIXEL_PATCH
    weights_id = "none:centred+const0.05"
    # About a pooled token's spread of centred pixels on the tiny suites (std 0.03-0.07): the
    # LayerNorm's scale then depends on the pixels and on the constant alike, so the pixels keep
    # most of their weight and a gain on them still shows.
    constant = 0.05

    def forward(self, images: Tensor) -> Tensor:
        patches = self.scaled(super().forward(images))
        return torch.cat([patches, torch.full_like(patches, self.constant)], dim=1)

    def scaled(self, centred: Tensor) -> Tensor:
        return centred


class NormalisedConstantBlockPixelsEncoder(ConstantBlockPixelsEncoder):
    """`pixels_ones` with each image's centred pixels divided by their standard deviation: the
    planted invariance of the robustness tier. A gain (brightness) or a contrast change about
    the image's mean scales the centred image by one factor, which the division takes out
    again: the features, and so the graft's MSE, stay where they were (up to rounding)."""

    weights_id = "none:centred-unit-std+const0.05"

    def scaled(self, centred: Tensor) -> Tensor:
        # clamp, not + eps: a scaled image then gives the same features up to rounding
        return centred / centred.std(dim=(1, 2, 3), keepdim=True).clamp_min(1e-6)


class TowerPatchPixelsEncoder(_KnownEncoder):
    """The image resized to 64 px (antialiased bilinear), mean-centred, cut in 16 x 16 px
    patches: (B, 3, H, W) -> (B, 768, 4, 4), channel c*256 + dy*16 + dx.

    Why beside `pixels`: the fixed wrapper averages an encoder's grid down to the backbone's, and
    averaging 8 px patches folds them into one mean patch (the sim suites' 128 px images are a
    16 x 16 grid of them; a 4 x 4 native grid keeps the mean 8 x 8 patch of each 32 x 32 px
    region, about its colour). This grid is coarse instead: pooled to 4 x 4 or finer it loses
    nothing, and each token is exactly the pixels a patch-16 tower reads at 64 px."""

    patch = 16  # the spec's input_size (64) is the side it resizes to: a 4 x 4 grid
    channels = 3 * patch * patch
    weights_id = "none:centred-64px-p16"

    def forward(self, images: Tensor) -> Tensor:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"{self.spec.name} encoder needs (B, 3, H, W); got "
                             f"{tuple(images.shape)}")
        # mean 0, std 1: the shared resize alone, with no normalisation
        identity = (torch.zeros(1, 3, 1, 1, device=images.device),
                    torch.ones(1, 3, 1, 1, device=images.device))
        return centred_patches(resized_normalised(images, self.input_size, *identity),
                               self.patch)


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
    name="pixels_ones", timm_name=None, input_size=64, layout="map",
    description="known answer: pixels plus a constant block, 384 ch, (H/8)x(W/8) grid; keeps "
                "the scene's brightness through the wrapper's LayerNorm"),
    ConstantBlockPixelsEncoder)

register(EncoderSpec(
    name="pixels_ones_norm", timm_name=None, input_size=64, layout="map",
    description="known answer: pixels_ones with each image's pixels divided by their std, "
                "384 ch; blind to a brightness or contrast change (a planted invariance)"),
    NormalisedConstantBlockPixelsEncoder)

register(EncoderSpec(
    name="pixels_p16", timm_name=None, input_size=64, layout="map",
    description="known answer: the image at 64 px, mean-centred, in 16x16 patches, 768 ch, 4x4 "
                "grid; what a patch-16 tower reads at 64 px, kept whole by pooling to 4x4 or "
                "finer"), TowerPatchPixelsEncoder)

register(EncoderSpec(
    name="blind", timm_name=None, input_size=64, layout="map",
    description="known answer: constant ones, 16 ch, 2x2 grid; no visual information"),
    BlindEncoder)


# The known-answer ladder: the image at falling resolution, then with rising noise,
# down to blind. A rung is the image's r x r block means (minus 0.5) flattened into 3*r*r
# channels of one token, repeated on a 2x2 grid (the smallest grid an encoder gives:
# tests/test_encoders.py); one token, because a screen averages each camera's grid, and a grid
# of pixel patches averages to the mean patch, which has lost where things are. 4 x 4 is a
# function of 8 x 8, and each noisy rung is the one before plus more of the same draw, so no
# rung can hold more about the scene than the one above. Why not other rungs, as measured on
# the tiny world (smolvla, spatial): at 16 x 16 LogME's evidence fell below 8 x 8's (0.154 vs
# 0.171; 1,500 columns on ~1,000 windows), and k-NN ranked 1 x 1 (the mean colour, 3 columns)
# above 8 x 8: an estimator's score is not monotone in information across widths, so below
# 4 x 4 the ladder adds noise at a fixed width instead (as tests/test_screen.py's ladder does).
# `pytest bench --screen --encoders <LADDER> --screen-keep all` checks a screen against it.
LADDER_RUNGS = ((8, 0.0), (4, 0.0), (4, 0.02), (4, 0.03))  # (resolution, noise sigma)


def _rung_name(resolution: int, sigma: float) -> str:
    return f"pixels_res{resolution}" + (f"_noise{round(sigma * 100)}" if sigma else "")


LADDER = (*(_rung_name(r, s) for r, s in LADDER_RUNGS), "blind")


def image_noise(images: Tensor) -> Tensor:
    """A standard normal draw per image, seeded by the image's bytes: the same image always gets
    the same draw (the feature store may read a frame in any batch), different images differ."""
    draws = []
    for image in images.detach().float().cpu():
        seed = int.from_bytes(hashlib.sha256(image.numpy().tobytes()).digest()[:8], "little")
        draws.append(torch.randn(image.shape, generator=torch.Generator().manual_seed(seed)))
    return torch.stack(draws).to(images.device)


class LowResolutionEncoder(_KnownEncoder):
    """(B, 3, H, W) -> (B, 3*r*r, 2, 2): the image's r x r block means minus 0.5, plus `noise`
    times a per-image normal draw, in every cell."""

    resolution = 1
    noise = 0.0

    @property
    def channels(self) -> int:
        return 3 * self.resolution ** 2

    def forward(self, images: Tensor) -> Tensor:
        h, w = images.shape[-2:]
        if h % self.resolution or w % self.resolution:
            raise ValueError(f"{self.spec.name} needs H, W multiples of {self.resolution}; got "
                             f"{tuple(images.shape)}")
        coarse = F.adaptive_avg_pool2d(images.float(), self.resolution) - 0.5
        if self.noise:
            coarse = coarse + self.noise * image_noise(images)[..., :self.resolution,
                                                               :self.resolution]
        return coarse.flatten(1)[:, :, None, None].expand(-1, -1, 2, 2).contiguous()


for _r, _sigma in LADDER_RUNGS:
    register(EncoderSpec(
        name=_rung_name(_r, _sigma), timm_name=None, input_size=64, layout="map",
        description=f"known-answer ladder: the image as {_r}x{_r} block means in one token "
                    f"({3 * _r * _r} ch)" + (f", plus noise sigma {_sigma}" if _sigma else "")
                    + "; less visual information than the rung above"),
        type(f"LowResolution{_r}Noise{round(_sigma * 100)}", (LowResolutionEncoder,),
             # weights_id names the definition: the feature store keys on it
             {"resolution": _r, "noise": _sigma,
              "weights_id": f"none:{_rung_name(_r, _sigma)}"}))
