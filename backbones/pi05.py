"""pi0.5 (LeRobot 0.6.1 `PI05Policy`) behind the `Backbone` interface, real or tiny.

The adapter is backbones.paligemma's (loading: paligemma_load), shared with pi0: the graft point is
`PaliGemmaWithExpertModel.embed_image` (modeling_pi05.py:284-293), SigLIP -> multi_modal_projector,
with no scaling of image embeddings afterwards (:492-502); the loss calls the INNER
`PI05Pytorch.forward` (:564-611), because `PI05Policy.forward` (:1058-1096) takes no noise/time
and counts padded chunk steps. pi0.5's own: the state enters only as discretised text in the
prompt (processor_pi05.py ~63-75), so the inner forward takes no state; QUANTILES normalisation.
"""

from __future__ import annotations

import os
from pathlib import Path

from backbones import paligemma, paligemma_load
from backbones.base import BackboneInfo
from backbones.paligemma import PaliGemmaBackbone

MARKER_FILE = "graftbench_pi05.json"  # written by save_pretrained: tiny arch, cameras, rename map

NATIVE_FEATURE_DOC = (
    "SigLIP vision tower last_hidden_state (after its post-layernorm, BEFORE PaliGemma's "
    "multi_modal_projector), computed from the image the policy feeds embed_image (resized with "
    "padding to config.image_resolution, scaled to [-1, 1]); tokens reshaped row-major to "
    "(B, C, h, w): (B, 1152, 16, 16) for pi05_base, (B, 32, 4, 4) for the tiny build"
)

FAMILY = paligemma.PaliGemmaFamily(
    name="pi05", label="pi0.5", policy_type="pi05", class_prefix="PI05", marker_file=MARKER_FILE,
    normalization="QUANTILES", stat_names=("q01", "q99"),  # pi0.5 normalises by quantiles
    state_token=False, native_feature_doc=NATIVE_FEATURE_DOC,
)

INFO_REAL = BackboneInfo(
    name="pi05",
    native_grid=(16, 16),  # 224 px / patch 14 (configuration_pi05.py:25; SigLIP So400m)
    lm_width=2048,  # gemma_2b width (modeling_pi05.py:169-177)
    chunk_size=50,
    max_action_dim=32,
    num_denoise_steps=10,
    native_feature_doc=NATIVE_FEATURE_DOC,
)


class PI05Backbone(PaliGemmaBackbone):
    """A real `PI05Policy` with its own pre/post processors (see backbones.base for the contract)."""

    family = FAMILY


def build_tiny_policy(
    stats: dict,
    camera_keys=("observation.images.image", "observation.images.wrist_image"),
    image_hw: tuple[int, int] = (64, 64),
    state_dim: int = 8,
    action_dim: int = 7,
    chunk_size: int = 10,
    seed: int = 0,
) -> PI05Backbone:
    """A real PI05Policy with tiny sizes (~0.2M parameters), offline, deterministic from `seed`."""
    return paligemma.build_tiny_policy(PI05Backbone, stats, camera_keys, image_hw, state_dim,
                                       action_dim, chunk_size, seed)


def save_pretrained(backbone: PI05Backbone, folder: str | os.PathLike) -> Path:
    """Policy (config + safetensors), both processors and our marker into `folder`."""
    return paligemma.save_pretrained(backbone, folder)


def load_policy(path_or_repo_id: str, stats: dict | None = None, *, revision: str | None = None,
                device: str | None = None) -> PI05Backbone:
    """A saved folder (tiny or real) or a hub repo id from the HF cache (backbones.paligemma_load)."""
    return paligemma_load.load_policy(PI05Backbone, path_or_repo_id, stats, revision=revision,
                                      device=device)


def artifacts(repo_id: str, revision: str | None, needed_by: str) -> list:
    """What loading `repo_id` reads from the hub: the checkpoint and the PaliGemma tokenizer."""
    return paligemma_load.artifacts(repo_id, revision, needed_by)


def check_real_shapes() -> dict[str, int]:
    """Build the REAL pi0.5 model on the meta device (no weights) and embed one 224 px image.

    Returns {"tokens_per_camera": 256, "lm_width": 2048} for LeRobot's default PI05Config.
    """
    return paligemma.check_real_shapes(FAMILY)


def _adapt_real_config(config, stats: dict | None) -> tuple[dict[str, str], tuple[str, ...]]:
    """LIBERO view of a released pi0.5 config (in place): rename map, cameras kept."""
    return paligemma_load.adapt_real_config(config, stats, FAMILY)
