"""LeRobot policy plugin: a graftbench graft (timm encoder -> pooled to the native token grid ->
LayerNorm without affine -> Linear) in place of a VLA's vision tower, as LeRobot policy types.

Importing this module registers the config types `graft_smolvla`, `graft_pi05`, `graft_pi0` and
the processor step `graft_tokenizer_processor`; LeRobot finds the policy classes in
`modeling_graft` and the processor factories in `processor_graft` by its naming convention.
Light on purpose (every LeRobot CLI imports it at start): no timm, no model is built here.
Stands alone: it imports nothing of graftbench's; graftbench imports from it the backbone families
and their graft points (`families`) and the tiny PaliGemma build (`tiny_paligemma`), and from
its sibling package `graftcore` (same distribution, no LeRobot) the encoder and the graft
wrapper, so an export runs the code the harness measured.
"""

from lerobot_policy_graft import configuration_graft  # noqa: F401  (registers the config types)
from lerobot_policy_graft.configuration_graft import TRAIN_SCOPES  # noqa: F401
from lerobot_policy_graft.families import FAMILIES
from lerobot_policy_graft.processor_graft import GraftTokenizerProcessorStep  # noqa: F401

# LeRobot's policy type -> the config type of its graft ("pi05" -> "graft_pi05").
GRAFT_TYPES = {policy_type: f"graft_{policy_type}" for policy_type in FAMILIES}
