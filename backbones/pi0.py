"""pi0 (LeRobot 0.6.1 `PI0Policy`) behind the `Backbone` interface, real or tiny.

The adapter is backbones.paligemma's (loading: paligemma_load), shared with pi0.5 by composition:
this module is the PaliGemma adapter of the family `lerobot_policy_graft.families.PI0`. The graft
point is `PaliGemmaWithExpertModel.embed_image` (modeling_pi0.py:287-296), SigLIP ->
multi_modal_projector, with no scaling of image embeddings afterwards (embed_prefix :487-527); the
loss calls the INNER `PI0Pytorch.forward` (:592-641), because `PI0Policy.forward` (:1094-1131)
takes no noise/time and counts padded chunk steps. pi0's own: the state is ONE continuous token,
`state_proj` of the padded normalised state at the head of the action expert's suffix
(:529-549), so the inner forward takes it (the adapter pads it with the policy's own
`prepare_state`, :1048-1051); the time is concatenated with each action token and mixed by an
MLP (:558-575; no adaRMS); MEAN_STD normalisation of state and action (configuration_pi0.py:71-77);
tokenizer length 48 (:103). lerobot/pi0_base saved its pre-processor with device cuda
(docs/HUB_FACTS.md).
"""

from __future__ import annotations

from lerobot_policy_graft.families import PI0

from backbones.paligemma_load import paligemma_adapter

_ADAPTER = paligemma_adapter(PI0, __name__, hub_release_device="cuda")
(FAMILY, INFO_REAL, BACKBONE_CLASS, RENAMES_CAMERAS, MARKER_FILE, build_tiny_policy,
 save_pretrained, load_policy, check_real_shapes, artifacts, write_hub_release) = _ADAPTER
PI0Backbone = BACKBONE_CLASS
