"""LeRobot's PaliGemma policies (pi0.5 `PI05Policy`, pi0 `PI0Policy`; lerobot 0.6.1) behind the
`Backbone` interface: everything the two adapters share.

Both are one `PaliGemmaWithExpertModel` (modeling_pi05.py / modeling_pi0.py): the same graft point
`embed_image` (SigLIP -> multi_modal_projector, :284-293 / :287-296, no scaling of image
embeddings afterwards), the same image preparation, time distribution, Euler sampler and hub
tokenizer (google/paligemma-3b-pt-224). What differs is named by a `PaliGemmaFamily`
(lerobot_policy_graft.families: the class the exported plugin shares, with the graft point):
- the state: pi0.5 discretises it into the prompt (processor_pi05.py ~63-75); pi0 projects it to
  ONE continuous token at the head of the action expert's suffix (`state_proj`, modeling_pi0.py
  :529-549), so its inner forward takes the state as an argument (:592);
- the time: adaRMS conditioning of the expert (pi0.5) vs. concatenated with each action token and
  mixed by an MLP (pi0, :558-575): inside LeRobot's forward, nothing the adapter touches;
- normalisation: QUANTILES (pi0.5) vs. MEAN_STD (pi0) for state and action;
- tokenizer length: 200 (pi0.5) vs. 48 (pi0).

The loss calls the INNER model forward (PI05Pytorch.forward :564-611, PI0Pytorch.forward :592-641),
because the policies' own `forward` takes no noise/time and counts padded chunk steps. Loading a
saved folder or a hub release: backbones.paligemma_load.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor

from lerobot_policy_graft.families import PaliGemmaFamily

from backbones import hub
from backbones.base import Backbone, BackboneInfo, only_step
from backbones.tiny_paligemma import (
    LEROBOT_PIN,
    TOKENIZER_DIRNAME,
    TinyPaliGemmaArch,
    ensure_tiny_tokenizer,
    require_pinned_lerobot,
    tiny_paligemma_patches,
    tiny_vocabulary,
)
from ondisk.paths import cache_dir

PALIGEMMA_TOKENIZER_REPO = "google/paligemma-3b-pt-224"  # processor_pi05.py:141, processor_pi0.py:141
TOKENIZER_SUBDIR = "tokenizer"  # the tiny tokenizer travels inside a saved tiny checkpoint
ACTION_KEY, STATE_KEY = "action", "observation.state"
PAD_KEY = "action_is_pad"
TOKENS_KEY = "observation.language.tokens"  # lerobot.utils.constants.OBS_LANGUAGE_TOKENS
TOKEN_MASK_KEY = "observation.language.attention_mask"


def marker_file(family: PaliGemmaFamily) -> str:
    """graftbench's marker in a saved folder: tiny arch, cameras, rename map."""
    return f"graftbench_{family.policy_type}.json"


def native_feature_doc(family: PaliGemmaFamily) -> str:
    return ("SigLIP vision tower last_hidden_state (after its post-layernorm, BEFORE PaliGemma's "
            "multi_modal_projector), computed from the image the policy feeds embed_image (resized "
            "with padding to config.image_resolution, scaled to [-1, 1]); tokens reshaped row-major "
            f"to (B, C, h, w): (B, 1152, 16, 16) for {family.policy_type}_base, (B, 32, 4, 4) for "
            "the tiny build")


def real_info(family: PaliGemmaFamily) -> BackboneInfo:
    """The base release's geometry, the same for pi0.5 and pi0: 224 px / patch 14 (SigLIP
    So400m; configuration_pi05.py:25, configuration_pi0.py:25), gemma_2b width
    (modeling_pi05.py:169-177, modeling_pi0.py:172-180), chunk 50, 32 padded action dims."""
    return BackboneInfo(name=family.policy_type, native_grid=(16, 16), lm_width=2048,
                        chunk_size=50, max_action_dim=32, num_denoise_steps=10,
                        native_feature_doc=native_feature_doc(family))


# Cameras: the base releases name theirs base_0_rgb / left_wrist_0_rgb / right_wrist_0_rgb
# (docs/HUB_FACTS.md); LIBERO's agent view feeds base_0_rgb and its wrist left_wrist_0_rgb
# (backbones.hub.CAMERA_LAYOUTS). The unmapped right_wrist slot would be fed as a -1 image with
# mask False (modeling_pi05.py:1009-1014, modeling_pi0.py:1039-1042). We drop unmapped cameras from
# the config instead: masked tokens neither attend nor shift position ids (cumsum of pad masks,
# modeling_pi05.py:584), so outputs are unchanged (bit-identical on the tiny build, see tests), and
# every embed_image call is one suite camera.


class PaliGemmaBackbone(Backbone):
    """A real LeRobot PaliGemma policy with its own pre/post processors (contract: backbones.base).
    Subclasses set `family`."""

    family: PaliGemmaFamily

    def __init__(
        self,
        policy,  # lerobot PI05Policy / PI0Policy
        preprocessor,  # lerobot PolicyProcessorPipeline (raw batch -> prepared batch)
        postprocessor,  # lerobot PolicyProcessorPipeline (normalised actions -> raw)
        camera_keys: tuple[str, ...],
        tiny_arch: TinyPaliGemmaArch | None = None,
        rename_map: dict[str, str] | None = None,
    ) -> None:
        self.policy = policy
        self.preprocessor = preprocessor
        self.postprocessor = postprocessor
        self.camera_keys = tuple(camera_keys)
        self.tiny_arch: TinyPaliGemmaArch | None = tiny_arch
        self.rename_map: dict[str, str] = dict(rename_map or {})
        self.info = _info_from_policy(policy, self.family)
        self.action_dim = policy.config.output_features[ACTION_KEY].shape[0]

    # -- processing -------------------------------------------------------------------------
    def preprocess(self, raw: dict) -> dict:
        return self.preprocessor(dict(raw))

    def normalize_actions(self, actions: Tensor) -> Tensor:
        return _on_action(only_step(self.preprocessor, "NormalizerProcessorStep"), actions)

    def unnormalize_actions(self, actions: Tensor) -> Tensor:
        # The step alone, not the whole post-processor: that one also moves actions to the CPU.
        return _on_action(only_step(self.postprocessor, "UnnormalizerProcessorStep"), actions)

    # -- graft point: image_embedder is the family's (backbones.base) ----------------------
    def native_tower_grid(self, image: Tensor) -> Tensor:
        tower = self.policy.model.paligemma_with_expert.paligemma.model.vision_tower
        tokens = tower(image.to(torch.float32)).last_hidden_state  # (B, h*w, C)
        batch, count, channels = tokens.shape
        side = math.isqrt(count)
        if side * side != count:
            raise RuntimeError(f"SigLIP gave {count} tokens, not a square grid")
        return tokens.transpose(1, 2).reshape(batch, channels, side, side)

    # -- loss and sampling ------------------------------------------------------------------
    def loss(self, batch: dict, noise: Tensor, time: Tensor) -> Tensor:
        """(B,) flow-matching loss: mean over real action dims, then over real (unpadded) steps.

        The action expert attends across the whole chunk, so the values held at padded steps
        would still reach real steps through x_t. They are set to the last real action first
        (what LeRobotDataset delivers past an episode end, so a no-op on its batches), making
        the loss a function of real steps only.
        """
        policy = self.policy
        images, img_masks = policy._preprocess_images(batch)  # the policy's own pixel prep
        tokens, masks = batch[TOKENS_KEY], batch[TOKEN_MASK_KEY]
        # pi0's continuous state token: the policy's own padding to max_state_dim.
        state = (policy.prepare_state(batch),) if self.family.state_token else ()
        is_pad = batch[PAD_KEY].to(batch[ACTION_KEY].device).bool()
        held = _hold_last_real_action(batch[ACTION_KEY], is_pad)
        actions = policy.prepare_action({ACTION_KEY: held})  # zero-pad to max_action_dim
        device = actions.device
        per_element = policy.model.forward(
            images, img_masks, tokens, masks, *state, actions, noise.to(device), time.to(device)
        )  # (B, chunk, max_action_dim)
        per_step = per_element[:, :, : self.action_dim].mean(dim=2)
        real_steps = (~is_pad).to(per_step.dtype)
        return (per_step * real_steps).sum(dim=1) / real_steps.sum(dim=1).clamp(min=1.0)

    def sample_time(self, batch_size: int, generator: torch.Generator) -> Tensor:
        # Beta(alpha, beta) * scale + offset (sample_time, modeling_pi05.py:473-481 and
        # modeling_pi0.py:477-485), drawn as X / (X + Y) with X, Y ~ Gamma because torch's Beta
        # takes no generator.
        cfg = self.policy.config
        alpha = torch.full((batch_size,), float(cfg.time_sampling_beta_alpha))
        beta = torch.full((batch_size,), float(cfg.time_sampling_beta_beta))
        x = torch._standard_gamma(alpha, generator=generator)
        y = torch._standard_gamma(beta, generator=generator)
        return (x / (x + y)) * cfg.time_sampling_scale + cfg.time_sampling_offset

    @torch.no_grad()
    def sample_actions(self, batch: dict, noise: Tensor) -> Tensor:
        # predict_action_chunk (modeling_pi05.py:1040-1056, modeling_pi0.py:1076-1092):
        # normalised actions (no post-processor), already cut to the real action dims; 10 Euler
        # steps by default.
        device = batch[TOKENS_KEY].device
        return self.policy.predict_action_chunk(batch, noise=noise.to(device, torch.float32))

    def language_model(self) -> torch.nn.Module:
        return self.policy.model.paligemma_with_expert.paligemma.model.language_model


def _on_action(step, actions: Tensor) -> Tensor:
    """Apply one (un)normaliser step to an action tensor alone (its device is kept)."""
    from lerobot.processor import TransitionKey, create_transition

    return step(create_transition(action=actions))[TransitionKey.ACTION]


def _hold_last_real_action(actions: Tensor, is_pad: Tensor) -> Tensor:
    """(B, T, A) actions with every padded step replaced by the latest real step before it."""
    steps = torch.arange(actions.shape[1], device=actions.device).expand_as(is_pad)
    latest_real = torch.cummax(torch.where(is_pad, 0, steps), dim=1).values  # (B, T)
    return torch.gather(actions, 1, latest_real[..., None].expand_as(actions))


def _info_from_policy(policy, family: PaliGemmaFamily) -> BackboneInfo:
    paligemma = policy.model.paligemma_with_expert.paligemma
    vision = paligemma.config.vision_config
    side = vision.image_size // vision.patch_size
    return BackboneInfo(
        name=family.policy_type,
        native_grid=(side, side),
        lm_width=paligemma.config.text_config.hidden_size,
        chunk_size=policy.config.chunk_size,
        max_action_dim=policy.config.max_action_dim,
        num_denoise_steps=policy.config.num_inference_steps,
        native_feature_doc=native_feature_doc(family),
    )


# -- building -------------------------------------------------------------------------------
def build_tiny_policy(
    backbone_cls: type[PaliGemmaBackbone],
    stats: dict,
    camera_keys=hub.LIBERO_CAMERAS,
    image_hw: tuple[int, int] = (64, 64),
    state_dim: int = 8,
    action_dim: int = 7,
    chunk_size: int = 10,
    seed: int = 0,
    arch: Mapping[str, Any] | None = None,
) -> PaliGemmaBackbone:
    """A real LeRobot policy of `backbone_cls.family` with tiny sizes, offline, deterministic
    from `seed`; `arch`: TinyPaliGemmaArch fields of another size of the tiny ladder
    (backbones.tiny_sizes), None the base size."""
    require_pinned_lerobot()
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors

    family = backbone_cls.family
    _check_stats(stats, state_dim, action_dim, family)
    arch = TinyPaliGemmaArch(**{"vocab_size": _round_up(len(tiny_vocabulary()), 64),
                                **(arch or {})})
    if image_hw[0] != image_hw[1] or image_hw[0] % arch.patch_size:
        raise ValueError(f"image_hw {image_hw} must be square and a multiple of patch {arch.patch_size}")
    tokenizer_dir = ensure_tiny_tokenizer(cache_dir() / TOKENIZER_DIRNAME)
    inputs = {key: PolicyFeature(FeatureType.VISUAL, (3, *image_hw)) for key in camera_keys}
    inputs[STATE_KEY] = PolicyFeature(FeatureType.STATE, (state_dim,))
    config = family.lerobot_class("configuration", "Config")(
        input_features=inputs,
        output_features={ACTION_KEY: PolicyFeature(FeatureType.ACTION, (action_dim,))},
        chunk_size=chunk_size,
        n_action_steps=chunk_size,
        image_resolution=tuple(image_hw),
        # The tiny prompts fit in ~40 tokens: pi0.5's 200 only costs time; pi0's own is 48.
        tokenizer_max_length=48,
        device="cpu",
    )
    with torch.random.fork_rng(devices=[]), tiny_paligemma_patches(arch, tokenizer_dir, family.policy_type):
        torch.manual_seed(seed)
        policy = family.lerobot_class("modeling", "Policy")(config)
        preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
    return backbone_cls(policy, preprocessor, postprocessor, camera_keys, tiny_arch=arch)


def save_pretrained(backbone: PaliGemmaBackbone, folder: str | os.PathLike) -> Path:
    """Policy (config + safetensors), both processors and our marker into `folder`."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    backbone.policy.save_pretrained(folder)
    backbone.preprocessor.save_pretrained(folder)
    backbone.postprocessor.save_pretrained(folder)
    marker = {
        "lerobot": LEROBOT_PIN,
        "camera_keys": list(backbone.camera_keys),
        "rename_map": backbone.rename_map,
        "tiny_arch": backbone.tiny_arch.to_dict() if backbone.tiny_arch else None,
    }
    if backbone.tiny_arch is not None:  # the tokenizer in use travels with the checkpoint
        tokenizer_step = only_step(backbone.preprocessor, "TokenizerProcessorStep")
        tokenizer_step.input_tokenizer.save_pretrained(folder / TOKENIZER_SUBDIR)
    (folder / marker_file(backbone.family)).write_text(json.dumps(marker, indent=2, sort_keys=True))
    return folder


def check_real_shapes(family: PaliGemmaFamily) -> dict[str, int]:
    """Build the family's REAL model on the meta device (no weights) and embed one 224 px image.

    Returns {"tokens_per_camera": 256, "lm_width": 2048} for LeRobot's default configs.
    """
    require_pinned_lerobot()
    config = family.lerobot_class("configuration", "Config")(device="cpu")
    with torch.device("meta"):
        model = family.lerobot_class("modeling", "Pytorch")(config)
        image = torch.empty(1, 3, *config.image_resolution)
        embedded = model.paligemma_with_expert.embed_image(image)  # (1, N, lm_width), meta
    return {"tokens_per_camera": int(embedded.shape[1]), "lm_width": int(embedded.shape[2])}


def _check_stats(stats: dict, state_dim: int, action_dim: int, family: PaliGemmaFamily) -> None:
    for key, dim in ((STATE_KEY, state_dim), (ACTION_KEY, action_dim)):
        for name in family.stat_names:
            values = stats.get(key, {}).get(name)
            if values is None or len(values) != dim:
                raise ValueError(
                    f"stats[{key!r}][{name!r}] must have {dim} values ({family.label} uses "
                    f"{family.normalization} normalisation), got "
                    f"{None if values is None else len(values)}"
                )


def _round_up(value: int, multiple: int) -> int:
    return -(-value // multiple) * multiple
