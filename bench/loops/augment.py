"""Image augmentation shared by native training (bench.resources.releases) and graft training
(bench.cell.inputs): one definition, so "image shift N" means the same in both."""

from __future__ import annotations

import torch


def shift_images(images: torch.Tensor, pad: int, generator: torch.Generator) -> torch.Tensor:
    """(B, 3, H, W) images, each moved by its own random (dx, dy) in [-pad, pad] (DrQ's
    pad-and-crop, edges replicated): a policy trained on them cannot key on exact pixel
    positions."""
    if pad <= 0:
        return images
    n, _, h, w = images.shape
    padded = torch.nn.functional.pad(images, (pad, pad, pad, pad), mode="replicate")
    offsets = torch.randint(0, 2 * pad + 1, (n, 2), generator=generator).tolist()
    return torch.stack([padded[i, :, y:y + h, x:x + w] for i, (x, y) in enumerate(offsets)])
