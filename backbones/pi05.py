"""pi0.5 (LeRobot 0.6.1 `PI05Policy`) behind the `Backbone` interface, real or tiny.

The adapter is backbones.paligemma's (loading: paligemma_load), shared with pi0: the graft point is
`PaliGemmaWithExpertModel.embed_image` (modeling_pi05.py:284-293), SigLIP -> multi_modal_projector,
with no scaling of image embeddings afterwards (:492-502); the loss calls the INNER
`PI05Pytorch.forward` (:564-611), because `PI05Policy.forward` (:1058-1096) takes no noise/time
and counts padded chunk steps. pi0.5's own: the state enters only as discretised text in the
prompt (processor_pi05.py ~63-75), so the inner forward takes no state; QUANTILES normalisation.
"""

from __future__ import annotations

import sys
from pathlib import Path

from backbones import hub_world, paligemma, paligemma_load
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


# The module functions the registry reads: the PaliGemma family's, bound to PI05Backbone.
_ADAPTER = paligemma_load.adapter_functions(PI05Backbone)
build_tiny_policy = _ADAPTER["build_tiny_policy"]
save_pretrained = _ADAPTER["save_pretrained"]
load_policy = _ADAPTER["load_policy"]
artifacts = _ADAPTER["artifacts"]
check_real_shapes = _ADAPTER["check_real_shapes"]
BACKBONE_CLASS = PI05Backbone
RENAMES_CAMERAS = False  # a checkpoint is loaded with its saved camera names


def write_hub_release(hub_cache: Path, repo_id: str, revision: str | None) -> None:
    """lerobot/pi05_base shaped: its processors saved with device cpu (docs/HUB_FACTS.md)."""
    hub_world.write_paligemma_release(sys.modules[__name__], hub_cache, repo_id, revision,
                                      device="cpu")
