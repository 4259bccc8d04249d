"""Config types of grafted policies: LeRobot's own SmolVLA / pi0.5 / pi0 configs plus what the
graft is (encoder architecture and preprocessing, token grid, projector width) and what trains.

Every field is plain data LeRobot's CLI can read and set (`--policy.train_scope=...`).
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field

from lerobot.configs import PreTrainedConfig
from lerobot.policies.pi0.configuration_pi0 import PI0Config
from lerobot.policies.pi05.configuration_pi05 import PI05Config
from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

# What `lerobot-train` optimises (the policy's get_optim_params); everything else is frozen.
# "projector+policy": what LeRobot itself trains of the base policy (its freeze flags) and the
# projector.
TRAIN_SCOPES = {
    "projector": ("graft.projector.",),
    "projector+encoder": ("graft.projector.", "graft.encoder."),
    "projector+policy": None,
}
ENCODER_LAYOUTS = ("tokens", "map")


@dataclass
class GraftFields:
    """The graft: a timm architecture by name (+ constructor overrides, JSON), fed the camera
    images in [0, 1] resized to `encoder_input_size` and normalised by its own mean/std; its grid
    pooled to `graft_grid`, then LayerNorm (no affine) and Linear(encoder_channels -> LM width)."""

    encoder_name: str = ""  # graftbench's encoder name, for the record
    encoder_timm_name: str = ""
    encoder_timm_kwargs: str = "{}"  # JSON: timm.create_model overrides (tiny architectures)
    encoder_input_size: int = 224
    encoder_mean: list[float] = field(default_factory=lambda: [0.5, 0.5, 0.5])
    encoder_std: list[float] = field(default_factory=lambda: [0.5, 0.5, 0.5])
    encoder_num_prefix_tokens: int = 0
    encoder_layout: str = "tokens"
    encoder_channels: int = 0
    graft_grid: list[int] = field(default_factory=lambda: [8, 8])
    train_scope: str = "projector"
    graft_cell: str = ""  # the graftbench cell this graft was measured as
    tiny_arch: str = ""  # JSON of tiny_paligemma.TinyPaliGemmaArch: graftbench's tiny PaliGemma builds

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.train_scope not in TRAIN_SCOPES:
            raise ValueError(f"train_scope {self.train_scope!r} not in {sorted(TRAIN_SCOPES)}: "
                             "set --policy.train_scope to one of them")
        if self.encoder_layout not in ENCODER_LAYOUTS:
            raise ValueError(f"encoder_layout {self.encoder_layout!r} not in {ENCODER_LAYOUTS}")
        if len(self.graft_grid) != 2 or min(self.graft_grid) < 1:
            raise ValueError(f"graft_grid {self.graft_grid} must be [rows, cols], both >= 1")
        json.loads(self.encoder_timm_kwargs)  # fail at parse time, not at build time

    @property
    def timm_kwargs(self) -> dict:
        """encoder_timm_kwargs decoded (JSON lists -> tuples, as timm's signatures spell them)."""
        return {k: tuple(v) if isinstance(v, list) else v
                for k, v in json.loads(self.encoder_timm_kwargs).items()}


@PreTrainedConfig.register_subclass("graft_smolvla")
@dataclass
class GraftSmolVLAConfig(GraftFields, SmolVLAConfig):
    """SmolVLA with a graft for its vision tower + connector. `vlm_model_name` may be a folder
    relative to the checkpoint (the bundled tiny VLM): the policy resolves it there."""


@PreTrainedConfig.register_subclass("graft_pi05")
@dataclass
class GraftPI05Config(GraftFields, PI05Config):
    """pi0.5 with a graft for its SigLIP tower + projection."""


@PreTrainedConfig.register_subclass("graft_pi0")
@dataclass
class GraftPI0Config(GraftFields, PI0Config):
    """pi0 with a graft for its SigLIP tower + projection."""


def config_from_pretrained(source: str, revision: str | None = None) -> PreTrainedConfig:
    """PreTrainedConfig.from_pretrained(source, revision=revision), less the file it leaves
    behind: LeRobot 0.6.1 dumps the config into a NamedTemporaryFile(delete=False) for draccus
    and never removes it (a test run left ~140 in /tmp). Its temp files go to a private folder,
    removed on return. graftbench's adapters read checkpoints' configs through it too."""
    with tempfile.TemporaryDirectory(prefix="graftbench-config-") as private:
        before, tempfile.tempdir = tempfile.tempdir, private
        try:
            return PreTrainedConfig.from_pretrained(source, revision=revision)
        finally:
            tempfile.tempdir = before
