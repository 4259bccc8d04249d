"""Pooled encoder features: the grid pooled to the backbone's token grid, cached per suite.

`encode_pooled` is the one function that turns images into pooled features; the cache calls it
too, so the cached path and the encoder-in-the-loop path agree numerically.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Protocol

import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import Tensor

from bench.progress import Progress, say
from encoders.base import Encoder

# Bump when a change to pooling or encoding moves cached numbers on purpose.
FEATURES_VERSION = "1"


class FeatureSource(Protocol):
    """What the cache needs of a suite (bench.suites.base.Suite satisfies it)."""

    name: str
    fingerprint: str
    camera_keys: tuple[str, ...]
    state: Tensor  # (N, 8): only its length (the number of frames) is used here

    def images(self, frames: Tensor) -> dict[str, Tensor]: ...


def pool_grid(grid: Tensor, target: tuple[int, int]) -> Tensor:
    """(B, C, h, w) -> (B, rows*cols, C) by adaptive average pooling; tokens in row-major order."""
    rows, cols = target
    pooled = F.adaptive_avg_pool2d(grid, (rows, cols))  # (B, C, rows, cols)
    return pooled.flatten(2).transpose(1, 2)


def encoder_device(encoder: Encoder) -> torch.device:
    """Device of the encoder's parameters or buffers (CPU for parameter-free encoders)."""
    for tensor in (*encoder.parameters(), *encoder.buffers()):
        return tensor.device
    return torch.device("cpu")


def encode_pooled(encoder: Encoder, images_by_camera: dict[str, Tensor],
                  target_grid: tuple[int, int]) -> dict[str, Tensor]:
    """{camera: (B, 3, H, W) in [0,1]} -> {camera: (B, rows*cols, C) float32} on the encoder's
    device."""
    device = encoder_device(encoder)
    out = {}
    with torch.no_grad():
        for camera, images in images_by_camera.items():
            grid = encoder(images.to(device, torch.float32))
            out[camera] = pool_grid(grid.float(), target_grid).contiguous()
    return out


def feature_key(encoder: Encoder, suite: FeatureSource, target_grid: tuple[int, int]) -> str:
    """sha256 over everything that changes the cached numbers."""
    spec = encoder.spec
    fields = {
        "encoder": spec.name,
        "timm_name": spec.timm_name,
        "weights_id": encoder.weights_id,
        "input_size": getattr(encoder, "input_size", spec.input_size),
        "mean": list(spec.mean),
        "std": list(spec.std),
        "num_prefix_tokens": spec.num_prefix_tokens,
        "target_grid": list(target_grid),
        "suite": suite.fingerprint,
        "cameras": list(suite.camera_keys),
        "version": FEATURES_VERSION,
    }
    if encoder.weights_id.startswith("tiny"):  # tiny architecture is defined by its overrides
        fields["tiny_kwargs"] = repr(sorted(spec.tiny_kwargs.items()))
    blob = json.dumps(fields, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()


class FeatureCache:
    """Pooled features of every frame of a suite, one safetensors file per (encoder, grid, suite)."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def path(self, encoder: Encoder, suite: FeatureSource, target_grid: tuple[int, int]) -> Path:
        return self.root / f"{feature_key(encoder, suite, target_grid)}.safetensors"

    def pooled_features(self, encoder: Encoder, suite: FeatureSource,
                        target_grid: tuple[int, int], batch_size: int = 64,
                        progress=True) -> dict[str, Tensor]:
        """{camera: (N_frames, rows*cols, C) float32 on CPU}, computed once per key, then loaded."""
        path = self.path(encoder, suite, target_grid)
        if path.exists():
            return load_file(path)
        features = self._compute(encoder, suite, target_grid, batch_size, progress)
        self._write(path, features, encoder, suite, target_grid)
        return features

    def _compute(self, encoder: Encoder, suite: FeatureSource, target_grid: tuple[int, int],
                 batch_size: int, progress) -> dict[str, Tensor]:
        n_frames = int(suite.state.shape[0])
        if n_frames == 0:
            raise ValueError(f"suite {suite.name!r} has no frames to encode")
        chunks: dict[str, list[Tensor]] = {camera: [] for camera in suite.camera_keys}
        label = f"features {encoder.spec.name} / {suite.name} at {target_grid[0]}x{target_grid[1]}"
        say(progress, f"{label}: encoding {n_frames} frames x {len(suite.camera_keys)} cameras")
        bar = Progress(label, n_frames, progress)
        for start in range(0, n_frames, batch_size):
            frames = torch.arange(start, min(start + batch_size, n_frames))
            images = suite.images(frames)
            pooled = encode_pooled(encoder, {c: images[c] for c in suite.camera_keys},
                                   target_grid)
            for camera, feats in pooled.items():
                chunks[camera].append(feats.cpu())
            bar.update(int(frames[-1]) + 1, "frames")
        return {camera: torch.cat(parts) for camera, parts in chunks.items()}

    def _write(self, path: Path, features: dict[str, Tensor], encoder: Encoder,
               suite: FeatureSource, target_grid: tuple[int, int]) -> None:
        """Atomic: a crash mid-write never leaves a file that a later run would trust."""
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp-{os.getpid()}")
        metadata = {"encoder": encoder.spec.name, "weights_id": encoder.weights_id,
                    "suite": suite.name, "suite_fingerprint": suite.fingerprint,
                    "target_grid": f"{target_grid[0]}x{target_grid[1]}",
                    "version": FEATURES_VERSION}
        try:
            save_file(features, str(tmp), metadata=metadata)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
