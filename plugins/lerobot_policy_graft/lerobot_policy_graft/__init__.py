"""LeRobot policy plugin: a graftbench graft (timm encoder -> pooled to the native token grid ->
LayerNorm without affine -> Linear) in place of a VLA's vision tower, as LeRobot policy types.

Importing this module registers the config types `graft_smolvla`, `graft_pi05`, `graft_pi0` and
the processor step `graft_tokenizer_processor`; LeRobot finds the policy classes in
`modeling_graft` and the processor factories in `processor_graft` by its naming convention.
Light on purpose (every LeRobot CLI imports it at start): no timm, no model is built here.
"""

from lerobot_policy_graft.configuration_graft import (  # noqa: F401
    TRAIN_SCOPES, GraftPI0Config, GraftPI05Config, GraftSmolVLAConfig,
)
from lerobot_policy_graft.processor_graft import GraftTokenizerProcessorStep  # noqa: F401

GRAFT_TYPES = {"smolvla": "graft_smolvla", "pi05": "graft_pi05", "pi0": "graft_pi0"}
