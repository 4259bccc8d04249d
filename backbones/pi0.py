"""pi0 (LeRobot 0.6.1 `PI0Policy`) behind the `Backbone` interface, real or tiny.

The adapter is backbones.paligemma's (loading: paligemma_load), shared with pi0.5: the graft point is
`PaliGemmaWithExpertModel.embed_image` (modeling_pi0.py:287-296), SigLIP -> multi_modal_projector,
with no scaling of image embeddings afterwards (embed_prefix :487-527); the loss calls the INNER
`PI0Pytorch.forward` (:592-641), because `PI0Policy.forward` (:1094-1131) takes no noise/time and
counts padded chunk steps. pi0's own: the state is ONE continuous token, `state_proj` of the padded
normalised state at the head of the action expert's suffix (:529-549), so the inner forward takes
it (the adapter pads it with the policy's own `prepare_state`, :1048-1051); the time is
concatenated with each action token and mixed by an MLP (:558-575; no adaRMS); MEAN_STD
normalisation of state and action (configuration_pi0.py:71-77); tokenizer length 48 (:103).
"""

from __future__ import annotations

import sys
from pathlib import Path

from backbones import hub_world, paligemma, paligemma_load
from backbones.base import BackboneInfo
from backbones.paligemma import PaliGemmaBackbone

MARKER_FILE = "graftbench_pi0.json"  # written by save_pretrained: tiny arch, cameras, rename map

NATIVE_FEATURE_DOC = (
    "SigLIP vision tower last_hidden_state (after its post-layernorm, BEFORE PaliGemma's "
    "multi_modal_projector), computed from the image the policy feeds embed_image (resized with "
    "padding to config.image_resolution, scaled to [-1, 1]); tokens reshaped row-major to "
    "(B, C, h, w): (B, 1152, 16, 16) for pi0_base, (B, 32, 4, 4) for the tiny build"
)

FAMILY = paligemma.PaliGemmaFamily(
    name="pi0", label="pi0", policy_type="pi0", class_prefix="PI0", marker_file=MARKER_FILE,
    normalization="MEAN_STD", stat_names=("mean", "std"),  # configuration_pi0.py:71-77
    state_token=True, native_feature_doc=NATIVE_FEATURE_DOC,
)

INFO_REAL = BackboneInfo(
    name="pi0",
    native_grid=(16, 16),  # 224 px / patch 14 (configuration_pi0.py:25; SigLIP So400m)
    lm_width=2048,  # gemma_2b width (modeling_pi0.py:172-180)
    chunk_size=50,
    max_action_dim=32,
    num_denoise_steps=10,
    native_feature_doc=NATIVE_FEATURE_DOC,
)


class PI0Backbone(PaliGemmaBackbone):
    """A real `PI0Policy` with its own pre/post processors (see backbones.base for the contract)."""

    family = FAMILY


# The module functions the registry reads: the PaliGemma family's, bound to PI0Backbone.
_ADAPTER = paligemma_load.adapter_functions(PI0Backbone)
build_tiny_policy = _ADAPTER["build_tiny_policy"]
save_pretrained = _ADAPTER["save_pretrained"]
load_policy = _ADAPTER["load_policy"]
artifacts = _ADAPTER["artifacts"]
check_real_shapes = _ADAPTER["check_real_shapes"]
BACKBONE_CLASS = PI0Backbone
RENAMES_CAMERAS = False  # a checkpoint is loaded with its saved camera names


def write_hub_release(hub_cache: Path, repo_id: str, revision: str | None) -> None:
    """lerobot/pi0_base shaped: its pre-processor saved with device cuda (docs/HUB_FACTS.md)."""
    hub_world.write_paligemma_release(sys.modules[__name__], hub_cache, repo_id, revision,
                                      device="cuda")
