"""pi0.5 (LeRobot 0.6.1 `PI05Policy`) behind the `Backbone` interface, real or tiny.

The adapter is backbones.paligemma's (loading: paligemma_load), shared with pi0 by composition:
this module is the PaliGemma adapter of the family `lerobot_policy_graft.families.PI05`. The
graft point is `PaliGemmaWithExpertModel.embed_image` (modeling_pi05.py:284-293), SigLIP ->
multi_modal_projector, with no scaling of image embeddings afterwards (:492-502); the loss calls
the INNER `PI05Pytorch.forward` (:564-611), because `PI05Policy.forward` (:1058-1096) takes no
noise/time and counts padded chunk steps. pi0.5's own: the state enters only as discretised text
in the prompt (processor_pi05.py ~63-75), so the inner forward takes no state; QUANTILES
normalisation. lerobot/pi05_base saved its processors with device cpu (docs/HUB_FACTS.md).
"""

from __future__ import annotations

from lerobot_policy_graft.families import PI05

from backbones.paligemma_load import paligemma_adapter

_ADAPTER = paligemma_adapter(PI05, __name__, hub_release_device="cpu")
(FAMILY, INFO_REAL, BACKBONE_CLASS, RENAMES_CAMERAS, MARKER_FILE, build_tiny_policy,
 save_pretrained, load_policy, check_real_shapes, artifacts, write_hub_release) = _ADAPTER
PI05Backbone = BACKBONE_CLASS
