"""The small interface every backbone adapter offers the harness.

An adapter wraps a REAL LeRobot policy (SmolVLAPolicy, PI05Policy, PI0Policy) with its own pre/post
processors. The harness never reaches into policy internals itself: it asks the adapter.

Batches:
- raw batch (what the harness builds from a suite): {
    "<camera key>": (B, 3, H, W) float32 in [0, 1]  for each of `camera_keys` (LIBERO names),
    "observation.state": (B, S) float32,
    "action": (B, T, A) float32 raw units (T = chunk_size, A = real action dim, LIBERO 7),
    "action_is_pad": (B, T) bool,
    "task": list[str] of length B }
- prepared batch: `adapter.preprocess(raw)`: the policy's own pre-processor applied (rename to the
  policy's feature names, normalisation, tokenisation, device). Loss and sampling take this.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import ContextManager

import numpy as np
import torch
from lerobot_policy_graft.families import GraftFamily, ImageEmbedder  # noqa: F401
from torch import Tensor

from ondisk.libero_format import ACTION_KEY, STATE_KEY

# ImageEmbedder: fn(image) -> (B, N_tokens, lm_width), called once per camera, in `camera_keys`
# order, with the image tensor the policy itself would feed its vision tower (already
# resized/scaled by it).


class BackboneUnavailable(RuntimeError):
    """A real checkpoint or dependency is absent (offline cache miss): one actionable line."""


@dataclass(frozen=True)
class BackboneInfo:
    name: str
    native_grid: tuple[int, int]  # image tokens per camera as (rows, cols) entering the LM
    lm_width: int  # width of the LM input embeddings the projector must produce
    chunk_size: int
    max_action_dim: int  # padded action width inside the policy (32 for both)
    num_denoise_steps: int  # the sampler's default step count
    # Which tensor the native_wrapped control takes as "the native tower's features".
    native_feature_doc: str


class Backbone:
    """Adapter base. Subclasses: backbones.smolvla.SmolVLABackbone, backbones.pi05.PI05Backbone,
    backbones.pi0.PI0Backbone (the last two through backbones.paligemma.PaliGemmaBackbone)."""

    info: BackboneInfo
    policy: torch.nn.Module
    camera_keys: tuple[str, ...]  # dataset camera keys, in the order embed_image is called
    # Which LeRobot policy and where it embeds images: the class the exported plugin shares.
    family: GraftFamily

    # -- processing -------------------------------------------------------------------------
    def preprocess(self, raw: dict) -> dict:
        raise NotImplementedError

    def unnormalize_actions(self, actions: Tensor) -> Tensor:
        """(B, T, A) normalised -> raw units, through the policy's own post-processor."""
        raise NotImplementedError

    def normalize_actions(self, actions: Tensor) -> Tensor:
        """(B, T, A) raw -> the policy's normalised action space (what its loss sees)."""
        raise NotImplementedError

    # -- graft point ------------------------------------------------------------------------
    def image_embedder(self, fn: ImageEmbedder) -> ContextManager[None]:
        """Within the block, pixels -> LM input embeddings is `fn` instead of tower+connector:
        the family's graft point, where the exported plugin installs its graft too."""
        return self.family.grafted(self.policy, fn)

    def native_tower_grid(self, image: Tensor) -> Tensor:
        """The native tower's features as a grid, (B, C, h, w) float32 (native_wrapped control)."""
        raise NotImplementedError

    # -- loss and sampling ------------------------------------------------------------------
    def loss(self, batch: dict, noise: Tensor, time: Tensor) -> Tensor:
        """Per-sample flow-matching loss (B,), real action dims only, padded steps masked.

        noise: (B, chunk_size, max_action_dim); time: (B,) in (0, 1), drawn by the caller with
        `sample_time` so that the seed alone decides them.
        """
        raise NotImplementedError

    def sample_time(self, batch_size: int, generator: torch.Generator) -> Tensor:
        """(B,) flow-matching times from the backbone's own time distribution."""
        raise NotImplementedError

    @torch.no_grad()
    def sample_actions(self, batch: dict, noise: Tensor) -> Tensor:
        """The backbone's own sampler with caller noise; (B, chunk, A) normalised, real dims."""
        raise NotImplementedError

    def with_stats(self, stats: dict) -> "Backbone":
        """The same policy (shared, not copied) with processors normalising by `stats`: the
        features and devices the processors were loaded with are kept, only the stats change."""
        import copy

        from lerobot.processor.normalize_processor import hotswap_stats

        clone = copy.copy(self)
        clone.preprocessor = hotswap_stats(self.preprocessor, stats)
        clone.postprocessor = hotswap_stats(self.postprocessor, stats)
        return clone

    def normalizer_fingerprint(self) -> str:
        """12 hex chars over the state/action stats the pre-processor really normalises with."""
        return stats_fingerprint(normalizer_stats(self.preprocessor))

    # -- freezing ---------------------------------------------------------------------------
    def freeze(self) -> None:
        """Every policy parameter requires_grad=False and the policy in eval mode."""
        self.policy.eval()
        for p in self.policy.parameters():
            p.requires_grad_(False)

    def language_model(self) -> torch.nn.Module:
        """The frozen LM that the LoRA control adapts (its attention has q_proj/v_proj)."""
        raise NotImplementedError


def only_step(pipeline, step: type | str):
    """The single step of a LeRobot processor `pipeline` of class `step` (a class or its name)."""
    name = step if isinstance(step, str) else step.__name__
    steps = [s for s in pipeline.steps if type(s).__name__ == name]
    if len(steps) != 1:
        names = [type(s).__name__ for s in pipeline.steps]
        raise RuntimeError(f"expected one {name} among the processor steps {names}")
    return steps[0]


def stats_fingerprint(stats: dict, keys=(STATE_KEY, ACTION_KEY)) -> str:
    """12 hex chars over the state/action normalisation stats (sorted, float64 bytes)."""
    hasher = hashlib.sha256()
    for key in keys:
        for name in sorted(stats.get(key, {})):
            value = stats[key][name]
            array = value.detach().cpu().double().numpy() if torch.is_tensor(value) else np.asarray(value, dtype=np.float64)
            hasher.update(f"{key}.{name}".encode())
            hasher.update(np.ascontiguousarray(array).tobytes())
    return hasher.hexdigest()[:12]


def normalizer_stats(pipeline) -> dict:
    """The stats the pipeline's (un)normaliser actually uses, {key: {stat: tensor}}."""
    for step in pipeline.steps:
        if type(step).__name__ in ("NormalizerProcessorStep", "UnnormalizerProcessorStep"):
            return step._tensor_stats
    raise RuntimeError(f"{pipeline.name} has no (un)normaliser step")
