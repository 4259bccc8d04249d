"""What a cell feeds its graft or its policy: the input rules of bench.grid.kinds, implemented once.

For a graft of an encoder the rules apply to its pooled features (from the feature store, or
the encoder in the loop); for the native tower through the wrapper and for the released policy
as is, they apply to the images the policy sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from bench.loops.augment import shift_images
from bench.loops.encode import encode_pooled
from bench.grid.kinds import SAME, SHUFFLED, ZERO
from bench.suites.windows import raw_batch


@dataclass
class CellInputs:
    suite: object
    windows: Tensor  # held-out window frames
    perm: Tensor  # the fixed derangement of the windows (shuffled rule)
    chunk_size: int
    device: torch.device
    grid: tuple[int, int]
    encoder: object = None  # a graft's encoder (None: the policy's own tower, or no graft)
    features: dict | None = None  # camera -> stored pooled features (None: encoder in the loop)
    tower: bool = False
    train_shift: int = 0  # Protocol.graft_image_shift: training images moved by up to this (px)
    shift_seed: int = 0
    # The encoder's weights train (bench.grid.kinds tune_encoder): training features keep its
    # autograd graph; evaluation's do not.
    tune_encoder: bool = False
    train_frames: Tensor | None = None  # the split's training frames (global indices)

    @property
    def on_pixels(self) -> bool:
        """The rules act on images (the tower or the released policy), not on features."""
        return self.encoder is None

    # --- features of a graft of an encoder ------------------------------------------------------
    def pooled(self, frames: Tensor, source_frames: Tensor | None = None,
               grad: bool = False) -> dict[str, Tensor]:
        """Graft features of `frames` (from `source_frames`' pixels for shuffled images); `grad`:
        through the encoder's graph (encoder in the loop only)."""
        src = frames if source_frames is None else source_frames
        if self.features is not None:
            picked = {k: v[src] for k, v in self.features.items()}
            if self.device.type == "cuda":  # pinned host memory: the copy overlaps the compute
                picked = {k: v.pin_memory().to(self.device, non_blocking=True)
                          for k, v in picked.items()}
            return picked
        return encode_pooled(self.encoder, self.suite.images(src), self.grid, grad)

    def zero_pooled(self, n: int) -> dict[str, Tensor]:
        """The encoder's features of an all-zero image, for each of `n` samples."""
        blank = {k: torch.zeros((1, *self.suite.image_shape)) for k in self.suite.camera_keys}
        return {k: v.expand(n, -1, -1)
                for k, v in encode_pooled(self.encoder, blank, self.grid).items()}

    def eval_features(self, rule: str):
        """features_for(window positions, frames) of bench.loops.evaluate.score, or None."""
        if self.on_pixels:
            return None
        return {
            SAME: lambda pos, frames: self.pooled(frames),
            ZERO: lambda pos, frames: self.zero_pooled(len(frames)),
            SHUFFLED: lambda pos, frames: self.pooled(frames, self.windows[self.perm[pos]]),
        }[rule]

    # --- images the policy sees -----------------------------------------------------------------
    def eval_images(self, rule: str):
        """images_for(window positions, frames, images) of bench.loops.evaluate.score, or None."""
        if not self.on_pixels:
            return None
        return {
            SAME: None,
            ZERO: lambda pos, frames, imgs: {k: torch.zeros_like(v) for k, v in imgs.items()},
            SHUFFLED: lambda pos, frames, imgs: self.suite.images(self.windows[self.perm[pos]]),
        }[rule]

    # --- training batches -----------------------------------------------------------------------
    def train_batches(self, rule: str):
        """next_batch(frames) -> (raw batch, graft features or None) of bench.loops.train.fit."""
        shift = self.train_shift if rule != ZERO else 0
        needs_pixels = self.on_pixels or self.features is None or shift > 0
        shifts = torch.Generator().manual_seed(self.shift_seed)

        def next_batch(frames: Tensor):
            raw = raw_batch(self.suite, frames, self.chunk_size, with_images=needs_pixels)
            for k in self.suite.camera_keys:  # a graft ignores them; the pipeline wants them
                raw.setdefault(k, torch.zeros((len(frames), *self.suite.image_shape)))
            if shift:  # stored features cannot be shifted: the encoder runs on the moved pixels
                raw.update({k: shift_images(raw[k], shift, shifts) for k in self.suite.camera_keys})
            if self.on_pixels:
                if rule == ZERO:
                    raw.update({k: torch.zeros_like(raw[k]) for k in self.suite.camera_keys})
                return raw, None
            if rule == ZERO:
                return raw, self.zero_pooled(len(frames))
            if shift:
                return raw, encode_pooled(self.encoder, {k: raw[k] for k in self.suite.camera_keys},
                                          self.grid, self.tune_encoder)
            return raw, self.pooled(frames, grad=self.tune_encoder)

        return next_batch
