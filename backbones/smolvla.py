"""SmolVLA (LeRobot `SmolVLAPolicy`, lerobot 0.6.1) behind the graftbench `Backbone` interface.

Places in lerobot/policies/smolvla this adapter relies on (line numbers for 0.6.1):
- graft point: `SmolVLMWithExpertModel.embed_image` (smolvlm_with_expert.py ~202-215) = vision
  tower -> connector (pixel shuffle by scale_factor, Linear to the LM width). It is looked up on the
  instance by `VLAFlowMatching.embed_prefix` (modeling_smolvla.py ~580), which multiplies its output
  by sqrt(width) afterwards (~585): a grafted embedder keeps that scaling. Written once, in
  `lerobot_policy_graft.families.SMOLVLA`, which the exported plugin installs its graft with.
- images reach `embed_image` resized with padding and mapped to [-1, 1] (`prepare_images` ~334-380),
  one call per camera in `config.image_features` order.
- loss: `SmolVLAPolicy.forward(batch, noise, time, reduction="none")` (~277-332) cuts the padded
  action dims, zeroes `action_is_pad` steps and averages over the valid (step, dim) entries.
- sampling: `predict_action_chunk(batch, noise)` (~232-241, ~195-230) returns the Euler-integrated
  chunk cut to the real action dims and still NORMALISED (no post-processor). It calls
  `self.eval()` and fills an action queue; `sample_actions` below restores the mode and the queue.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Any, Mapping

import torch
from lerobot_policy_graft.families import SMOLVLA
from torch import Tensor

from backbones import hub_release, smolvla_load
from backbones.base import Backbone, BackboneInfo, only_step
from backbones.smolvla_load import VENDORED_VLM_DIR, VLM_REPO_ID, artifacts  # noqa: F401
from backbones.tiny_smolvla import REAL_VLM, real_shape_forward, tiny_config, tokens_per_camera
from ondisk.libero_format import (
    ACTION_KEY, IMAGE_KEYS, LIBERO_ACTION_DIM, LIBERO_STATE_DIM, STATE_KEY,
)

NATIVE_FEATURE_DOC = (
    "SmolVLM's SigLIP vision tower output, vision_model(pixels).last_hidden_state reshaped to "
    "(B, C, h, w): taken BEFORE the connector's pixel shuffle and Linear to the LM width "
    "(smolvla_base: C=768 on a 32x32 patch grid, shuffled by 4 into 8x8 = 64 tokens)."
)
INFO_REAL = BackboneInfo(
    name="smolvla",
    native_grid=(8, 8),
    lm_width=960,
    chunk_size=50,
    max_action_dim=32,
    num_denoise_steps=10,
    native_feature_doc=NATIVE_FEATURE_DOC,
)
# Assumed camera layout of lerobot/smolvla_base (its config lists observation.images.camera1/2/3,
# SO-100 views; not checked against the file here, which is not in this cache): LIBERO's agent
# view feeds camera1 and the wrist view camera2. camera3 is dropped from the config, which is what
# LeRobot itself does with a camera absent from the batch when empty_cameras=0 (prepare_images
# ~372-376), e.g. when fine-tuning smolvla_base on two-camera LIBERO.
SMOLVLA_BASE_RENAME = {
    "observation.images.image": "observation.images.camera1",
    "observation.images.wrist_image": "observation.images.camera2",
}
# VLAFlowMatching.sample_time (modeling_smolvla.py ~549-550): Beta(1.5, 1.0) * 0.999 + 0.001.
TIME_BETA_ALPHA, TIME_SCALE, TIME_OFFSET = 1.5, 0.999, 0.001


class SmolVLABackbone(Backbone):
    """A real SmolVLAPolicy and its own processors (the rename map lives in the preprocessor)."""

    family = SMOLVLA

    def __init__(self, policy, preprocessor, postprocessor, name: str = "smolvla"):
        from lerobot.processor import RenameObservationsProcessorStep

        self.policy = policy
        self.preprocessor = preprocessor
        self.postprocessor = postprocessor
        self.rename_map = dict(only_step(preprocessor, RenameObservationsProcessorStep).rename_map)
        dataset_key = {policy_key: key for key, policy_key in self.rename_map.items()}
        self.camera_keys = tuple(dataset_key.get(k, k) for k in policy.config.image_features)
        self.info = info_from_policy(policy, name)

    # -- processing -------------------------------------------------------------------------
    def preprocess(self, raw: dict) -> dict:
        missing = [k for k in self.camera_keys if k not in raw]
        if missing:
            raise KeyError(f"raw batch lacks camera(s) {missing}; SmolVLA reads {self.camera_keys}")
        batch = self.preprocessor(dict(raw))
        # SmolVLA silently drops missing cameras beyond `empty_cameras` (prepare_images ~372-376).
        absent = [k for k in self.policy.config.image_features if k not in batch]
        if absent:
            raise KeyError(f"renamed by {self.rename_map}, the batch lacks camera(s) {absent}")
        return batch

    def normalize_actions(self, actions: Tensor) -> Tensor:
        from lerobot.processor import NormalizerProcessorStep

        return self._apply_action_step(only_step(self.preprocessor, NormalizerProcessorStep), actions)

    def unnormalize_actions(self, actions: Tensor) -> Tensor:
        from lerobot.processor import UnnormalizerProcessorStep

        return self._apply_action_step(only_step(self.postprocessor, UnnormalizerProcessorStep), actions)

    @staticmethod
    def _apply_action_step(step, actions: Tensor) -> Tensor:
        from lerobot.processor import TransitionKey, create_transition

        return step(create_transition(action=actions))[TransitionKey.ACTION]

    # -- graft point: image_embedder is the family's (backbones.base) ----------------------
    def native_tower_grid(self, image: Tensor) -> Tensor:
        tower = self.policy.model.vlm_with_expert.get_vlm_model().vision_model
        pixels = image.to(dtype=tower.dtype)
        hidden = tower(pixel_values=pixels, patch_attention_mask=None).last_hidden_state
        patch = tower.config.patch_size
        rows, cols = image.shape[-2] // patch, image.shape[-1] // patch
        if rows * cols != hidden.shape[1]:
            raise RuntimeError(f"tower gave {hidden.shape[1]} patches for a {rows}x{cols} grid")
        grid = hidden.reshape(hidden.shape[0], rows, cols, hidden.shape[-1])
        return grid.permute(0, 3, 1, 2).float()

    # -- loss and sampling ------------------------------------------------------------------
    def loss(self, batch: dict, noise: Tensor, time: Tensor) -> Tensor:
        self._check_noise(batch, noise)
        steps = batch[ACTION_KEY].shape[1]
        if steps != self.info.chunk_size:
            raise ValueError(f"action chunk of {steps} steps; SmolVLA's is {self.info.chunk_size}")
        # LeRobot mixes caller noise/time with batch tensors without a device move
        # (modeling_smolvla.py ~700): move them here, as the pi0.5 adapter does.
        device = batch[ACTION_KEY].device
        per_sample, _ = self.policy.forward(
            batch, noise=noise.to(device), time=time.to(device), reduction="none"
        )
        return per_sample

    def sample_time(self, batch_size: int, generator: torch.Generator) -> Tensor:
        # Beta(a, 1) has CDF t**a, so u**(1/a) with u ~ U(0, 1) draws it from `generator` alone.
        uniform = torch.rand(batch_size, generator=generator, device=generator.device)
        time = uniform.pow(1.0 / TIME_BETA_ALPHA) * TIME_SCALE + TIME_OFFSET
        return time.to(device=self.policy.config.device, dtype=torch.float32)

    @torch.no_grad()
    def sample_actions(self, batch: dict, noise: Tensor) -> Tensor:
        self._check_noise(batch, noise)
        was_training = self.policy.training
        try:
            device = batch[STATE_KEY].device
            return self.policy.predict_action_chunk(dict(batch), noise=noise.to(device))
        finally:
            self.policy.reset()  # empty the action queue predict_action_chunk filled
            self.policy.train(was_training)

    def _check_noise(self, batch: dict, noise: Tensor) -> None:
        expected = (batch[STATE_KEY].shape[0], self.info.chunk_size, self.info.max_action_dim)
        if tuple(noise.shape) != expected:
            raise ValueError(f"noise has shape {tuple(noise.shape)}; SmolVLA needs {expected}")

    def language_model(self) -> torch.nn.Module:
        return self.policy.model.vlm_with_expert.get_vlm_model().text_model


def info_from_policy(policy, name: str = "smolvla") -> BackboneInfo:
    """The BackboneInfo a built SmolVLAPolicy implies (grid from its image resize and VLM)."""
    config = policy.config
    vlm_config = policy.model.vlm_with_expert.config
    if config.resize_imgs_with_padding is not None:
        width, height = config.resize_imgs_with_padding  # SmolVLA stores (width, height)
    else:
        height, width = next(iter(config.image_features.values())).shape[1:]
    step = vlm_config.vision_config.patch_size * vlm_config.scale_factor
    return BackboneInfo(
        name=name,
        native_grid=(height // step, width // step),
        lm_width=vlm_config.text_config.hidden_size,
        chunk_size=config.chunk_size,
        max_action_dim=config.max_action_dim,
        num_denoise_steps=config.num_steps,
        native_feature_doc=NATIVE_FEATURE_DOC,
    )


def build_tiny_policy(
    stats: dict,
    camera_keys=IMAGE_KEYS,
    image_hw: tuple[int, int] = (64, 64),
    state_dim: int = LIBERO_STATE_DIM,
    action_dim: int = LIBERO_ACTION_DIM,
    chunk_size: int = 10,
    seed: int = 0,
    *,
    device: str = "cpu",
    arch: Mapping[str, Any] | None = None,
) -> SmolVLABackbone:
    """A real SmolVLAPolicy on the tiny local SmolVLM (~0.4M params), same weights for a seed;
    `arch`: another size of the tiny ladder (backbones.tiny_sizes, tiny_smolvla.sized_vlm)."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    config = tiny_config(camera_keys, image_hw, state_dim, action_dim, chunk_size, device, arch)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        policy = SmolVLAPolicy(config)
    policy.to(device).eval()
    preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
    return SmolVLABackbone(policy, preprocessor, postprocessor)


def save_pretrained(backbone: SmolVLABackbone, folder) -> Path:
    """Policy weights + config and both processors into `folder`; load_policy restores it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    vlm_source = Path(backbone.policy.config.vlm_model_name)
    if vlm_source.is_dir() and vlm_source.resolve() != (folder / VENDORED_VLM_DIR).resolve():
        shutil.copytree(vlm_source, folder / VENDORED_VLM_DIR, dirs_exist_ok=True)
    backbone.policy.save_pretrained(folder)
    backbone.preprocessor.save_pretrained(folder)
    backbone.postprocessor.save_pretrained(folder)
    return folder


def check_real_shapes() -> dict:
    """smolvla_base's architecture built offline without weights; token grid and LM width checked.

    See tiny_smolvla.real_shape_forward: the policy on the meta device from SmolVLM2-500M's
    numbers, one 512 px image through a one-layer CPU copy of its tower and its real connector.
    """
    policy, tower_out, tokens = real_shape_forward()
    info = info_from_policy(policy)
    shapes = {
        "tokens_per_camera": tokens.shape[1],
        "native_grid": info.native_grid,
        "lm_width": tokens.shape[2],
        "tower_tokens": tower_out.shape[1],
        "tower_width": tower_out.shape[2],
        "expert_width": policy.model.vlm_with_expert.expert_hidden_size,
        "parameters": sum(p.numel() for p in policy.parameters()),
    }
    rows, cols = tokens_per_camera(REAL_VLM)
    expected = {"tokens_per_camera": rows * cols, "native_grid": INFO_REAL.native_grid,
                "lm_width": INFO_REAL.lm_width, "chunk": INFO_REAL.chunk_size}
    got = {**shapes, "chunk": info.chunk_size}
    wrong = {k: (got[k], v) for k, v in expected.items() if got[k] != v}
    if wrong:
        raise RuntimeError(f"real SmolVLA shapes (got, expected) disagree with INFO_REAL: {wrong}")
    return shapes


def write_hub_release(hub_cache: Path, repo_id: str, revision: str | None) -> None:
    """lerobot/smolvla_base shaped: SO-100 cameras and dims, its hub quirks (backbones.hub_release)."""
    hub_release.write_smolvla_release(sys.modules[__name__], hub_cache, repo_id, revision)


BACKBONE_CLASS = SmolVLABackbone
RENAMES_CAMERAS = True  # load_policy takes rename_map, camera_keys, state_dim, action_dim


def load_policy(path_or_repo_id: str, stats: dict | None = None, **options) -> SmolVLABackbone:
    """A saved SmolVLA (local folder or hub id in the HF cache), fitted to LIBERO's features.
    `options` (rename_map, camera_keys, state_dim, action_dim, device, revision) and the rules:
    backbones.smolvla_load.load_parts."""
    return SmolVLABackbone(*smolvla_load.load_parts(path_or_repo_id, stats, **options))
