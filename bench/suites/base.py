"""A LIBERO-format suite held in memory as small per-frame arrays, images fetched on demand."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import torch
from torch import Tensor

class SuiteUnavailable(RuntimeError):
    """A real dataset is absent (offline cache miss) or lacks a required feature: one line."""


@dataclass
class Suite:
    name: str  # "spatial", "object", ...
    repo_id: str
    root: str  # local folder of the LeRobotDataset
    fps: int
    fingerprint: str  # hash of the data (used in cache keys)
    camera_keys: tuple[str, ...]
    image_shape: tuple[int, int, int]  # (3, H, W)
    state: Tensor  # (N, 8) float32
    action: Tensor  # (N, 7) float32
    episode_index: Tensor  # (N,) int64
    frame_index: Tensor  # (N,) int64, position inside its episode
    task_index: Tensor  # (N,) int64
    tasks: list[str]  # task_index -> task string
    stats: dict  # LeRobot dataset stats (meta.stats), used where a checkpoint has none
    # frames (B,) -> {camera: (B, 3, H, W) uint8 or float32 in [0, 1]}; set by the loader.
    image_loader: Callable[[Tensor], dict[str, Tensor]] | None = field(
        default=None, repr=False, compare=False
    )

    @property
    def num_frames(self) -> int:
        return int(self.action.shape[0])

    @property
    def episodes(self) -> list[int]:
        """Sorted episode indices present in the suite."""
        return torch.unique(self.episode_index).tolist()

    def images(self, frames: Tensor) -> dict[str, Tensor]:
        """{camera: (B, 3, H, W) float32 in [0, 1]} for global frame indices (B,)."""
        if self.image_loader is None:
            raise ValueError(f"suite {self.name!r} was built without an image loader")
        frames = torch.as_tensor(frames, dtype=torch.long).reshape(-1)
        out = {}
        for camera, image in self.image_loader(frames).items():
            if tuple(image.shape[1:]) != tuple(self.image_shape):
                raise ValueError(
                    f"suite {self.name!r} camera {camera!r}: images of shape "
                    f"{tuple(image.shape[1:])}, expected image_shape {tuple(self.image_shape)} "
                    "(C, H, W); regenerate the suite or fix image_shape"
                )
            out[camera] = image.float().div_(255.0) if image.dtype == torch.uint8 else image.float()
        return out
