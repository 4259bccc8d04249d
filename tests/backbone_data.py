"""Test data for every backbone adapter: LIBERO-like cameras, stats, raw batches, fixed noise.

The stats carry mean/std AND quantiles (pi0 and SmolVLA normalise by mean/std, pi0.5 by quantiles)
and per-camera entries, as LeRobot datasets have them.
"""

from __future__ import annotations

import importlib

import numpy as np
import torch

from backbones import BACKBONES

CAMERAS = ("observation.images.image", "observation.images.wrist_image")
CHUNK, STATE_DIM, ACTION_DIM = 10, 8, 7
# One family per adapter module: smolvla_libero is smolvla's module, pi05_libero pi05's.
FAMILIES = tuple(sorted({entry.module for entry in BACKBONES.values()}))


def family_name(module_path: str) -> str:
    """"backbones.pi05" -> "pi05": the adapter module's own name (test ids)."""
    return module_path.rsplit(".", 1)[-1]


def policy_type(module_path: str) -> str:
    """The LeRobot policy type the registry says this adapter module loads."""
    (kind,) = {e.policy_type for e in BACKBONES.values() if e.module == module_path}
    return kind


def adapter(module_path: str):
    """The adapter module (backbones.seam.AdapterModule) of a registry entry."""
    return importlib.import_module(module_path)


def make_stats(state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM, cameras=CAMERAS) -> dict:
    def one(dim: int, scale: float) -> dict:
        spread = np.linspace(0.5, 2.0, dim) * scale
        return {
            "mean": np.linspace(-0.2, 0.3, dim), "std": spread / 2, "min": -spread * 1.5,
            "max": spread * 1.5, "q01": -spread, "q99": spread,
        }
    stats = {"observation.state": one(state_dim, 1.0), "action": one(action_dim, 0.5)}
    for camera in cameras:  # present, as in LeRobot datasets; the VISUAL mode is IDENTITY
        stats[camera] = {"mean": np.full((3, 1, 1), 0.5), "std": np.full((3, 1, 1), 0.25)}
    return stats


def make_raw(batch: int = 2, seed: int = 0, cameras=CAMERAS) -> dict:
    """A raw batch (backbones.base): images (B, 3, 64, 64) in [0, 1], state, action chunk, task."""
    g = torch.Generator().manual_seed(seed)
    raw = {key: torch.rand(batch, 3, 64, 64, generator=g) for key in cameras}
    raw["observation.state"] = torch.randn(batch, STATE_DIM, generator=g)
    raw["action"] = torch.randn(batch, CHUNK, ACTION_DIM, generator=g) * 0.3
    raw["action_is_pad"] = torch.zeros(batch, CHUNK, dtype=torch.bool)
    raw["task"] = ["pick up the red block and place it on the plate", "open the top drawer"][:batch]
    return raw


def fixed_noise_time(backbone, batch: int, seed: int = 1):
    """(noise (B, CHUNK, max_action_dim), time (B,)) from one seeded generator."""
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(batch, CHUNK, backbone.info.max_action_dim, generator=g)
    return noise, backbone.sample_time(batch, g)


def build_tiny(module, seed: int = 0, cameras=CAMERAS, stats: dict | None = None):
    """The tiny build of adapter `module`, frozen."""
    backbone = module.build_tiny_policy(stats or make_stats(cameras=cameras), cameras,
                                        chunk_size=CHUNK, seed=seed)
    backbone.freeze()
    return backbone
