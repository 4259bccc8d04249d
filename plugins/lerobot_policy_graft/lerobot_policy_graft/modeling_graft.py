"""Grafted policies: LeRobot's own SmolVLAPolicy / PI05Policy / PI0Policy, with ONLY the image
embedding replaced: camera pixels in [0, 1] -> timm encoder (its own resize and mean/std) ->
grid pooled to the native token grid -> LayerNorm (no affine) -> Linear, the fixed wrapper of
external.graft that graftbench measured with.

Loading is strict (LeRobot's SmolVLA loads with strict=False and only logs; pi0 / pi0.5 print and
keep random weights): a missing or unexpected key raises. Folders a config names relative to the
checkpoint (the bundled tiny VLM) resolve against it, and are copied along when it is saved.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import shutil
from pathlib import Path

import torch
from lerobot.configs import PreTrainedConfig
from lerobot.policies.pi0.modeling_pi0 import PI0Policy
from lerobot.policies.pi05.modeling_pi05 import PI05Policy
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
from torch import Tensor, nn

from external.graft import GraftFeed, Projector, pool_grid
from external.lerobot_config import config_from_pretrained
from lerobot_policy_graft.configuration_graft import (
    TRAIN_SCOPES, GraftPI0Config, GraftPI05Config, GraftSmolVLAConfig,
)

# The checkpoint folder being loaded: relative asset names in its config resolve against it.
_ASSET_ROOT: contextvars.ContextVar[Path | None] = contextvars.ContextVar("graft_assets",
                                                                          default=None)


@contextlib.contextmanager
def assets_at(folder: str | Path):
    """Within the block, relative asset names in a graft config resolve against `folder` (what
    from_pretrained does for the checkpoint it loads; bench.export for the folder it writes)."""
    token = _ASSET_ROOT.set(Path(folder).resolve())
    try:
        yield
    finally:
        _ASSET_ROOT.reset(token)


def build_encoder(config) -> nn.Module:
    """The config's timm architecture, random init (the checkpoint holds its weights), wrapped
    by graftbench's frozen TimmEncoder: (B, 3, H, W) in [0, 1] -> (B, C, h, w) float32."""
    import timm

    from encoders.base import EncoderSpec
    from encoders.timm_encoders import TimmEncoder

    spec = EncoderSpec(name=config.encoder_name or f"timm:{config.encoder_timm_name}",
                       timm_name=config.encoder_timm_name, input_size=config.encoder_input_size,
                       mean=tuple(config.encoder_mean), std=tuple(config.encoder_std),
                       num_prefix_tokens=config.encoder_num_prefix_tokens,
                       layout=config.encoder_layout)
    model = timm.create_model(config.encoder_timm_name, pretrained=False, num_classes=0,
                              **config.timm_kwargs)
    encoder = TimmEncoder(spec, model, config.encoder_input_size, weights_id="checkpoint")
    if encoder.channels != config.encoder_channels:
        raise ValueError(f"{config.encoder_timm_name} with {config.encoder_timm_kwargs} has "
                         f"{encoder.channels} channels, the config says {config.encoder_channels}")
    return encoder


class GraftHead(nn.Module):
    """Encoder + projector; `bind(batch)` encodes the batch's cameras for the embed_image calls
    that follow (one per camera, in `camera_keys` order)."""

    def __init__(self, config, lm_width: int) -> None:
        super().__init__()
        self.encoder = build_encoder(config)
        self.projector = Projector(config.encoder_channels, lm_width)
        self.grid = (int(config.graft_grid[0]), int(config.graft_grid[1]))
        self.camera_keys = tuple(config.image_features)
        self.train_encoder = "graft.encoder." in (TRAIN_SCOPES[config.train_scope] or ())
        self.feed = GraftFeed(self.projector, self.camera_keys, self.grid)

    def encode(self, images: Tensor) -> Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, rows*cols, C) pooled, as graftbench's encode_pooled."""
        device = next(self.encoder.parameters()).device
        images = images.to(device, torch.float32)
        if self.train_encoder and torch.is_grad_enabled():  # TimmEncoder.forward is no_grad
            grid = type(self.encoder).forward.__wrapped__(self.encoder, images)
        else:
            grid = self.encoder(images)
        return pool_grid(grid.float(), self.grid).contiguous()

    def bind(self, batch: dict) -> None:
        missing = [k for k in self.camera_keys if k not in batch]
        if missing:
            raise KeyError(f"the graft needs cameras {list(self.camera_keys)}; the batch lacks "
                           f"{missing} (has {sorted(k for k in batch if 'image' in k)}): map "
                           "them with --rename_map")
        features = {}
        for key in self.camera_keys:
            images = batch[key][:, -1] if batch[key].ndim == 5 else batch[key]
            features[key] = self.encode(images)
        self.feed.bind(features)


class _Grafted:
    """What the three grafted policies share; `_embed_owner()` is the module whose embed_image
    the base policy calls, `_lm_width()` the width the projector must produce."""

    policy_type = ""

    def _install_graft(self) -> None:
        self.graft = GraftHead(self.config, self._lm_width())
        object.__setattr__(self._embed_owner(), "embed_image", self._embed_image)
        prefixes = TRAIN_SCOPES[self.config.train_scope]
        if prefixes is not None:
            for name, param in self.named_parameters():
                param.requires_grad_(name.startswith(prefixes))
        self._asset_root = _ASSET_ROOT.get()

    def _embed_image(self, image: Tensor) -> Tensor:
        return self.graft.feed(image)

    def get_optim_params(self):
        prefixes = TRAIN_SCOPES[self.config.train_scope]
        return [p for name, p in self.named_parameters()
                if (p.requires_grad if prefixes is None else name.startswith(prefixes))]

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *, config: PreTrainedConfig | None = None,
                        **kwargs):
        """LeRobot's loader with strict=True: any missing or unexpected key raises."""
        kwargs.pop("strict", None)
        folder = _local_folder(pretrained_name_or_path, kwargs.get("revision"))
        if config is None:
            config = config_from_pretrained(str(folder))
        if not isinstance(config, cls.config_class):
            raise TypeError(f"{folder} holds a {config.type!r} config, not {cls.name!r}")
        with assets_at(folder):
            return PreTrainedPolicy.from_pretrained.__func__(
                cls, str(folder), config=config, strict=True, **kwargs)

    def _save_pretrained(self, save_directory: Path, state_dict=None) -> None:
        super()._save_pretrained(save_directory, state_dict=state_dict)
        for name in self._bundled_assets():
            source = self._asset_root / name if self._asset_root else None
            target = Path(save_directory) / name
            if source is not None and source.is_dir() and source.resolve() != target.resolve():
                shutil.copytree(source, target, dirs_exist_ok=True)

    def _bundled_assets(self) -> list[str]:
        return []


def _local_folder(name_or_path, revision: str | None) -> Path:
    path = Path(name_or_path)
    if path.is_dir():
        return path
    from huggingface_hub import snapshot_download

    return Path(snapshot_download(str(name_or_path), revision=revision))


def _resolved(name: str) -> str:
    """A config's asset name, resolved against the checkpoint being loaded when it is there."""
    root = _ASSET_ROOT.get()
    if root is not None and not Path(name).is_absolute() and (root / name).is_dir():
        return str(root / name)
    return name


class GraftSmolVLAPolicy(_Grafted, SmolVLAPolicy):
    config_class = GraftSmolVLAConfig
    name = "graft_smolvla"

    def __init__(self, config: GraftSmolVLAConfig, **kwargs):
        saved = config.vlm_model_name
        config.vlm_model_name = _resolved(saved)  # AutoConfig/AutoProcessor read it here only
        try:
            super().__init__(config, **kwargs)
        finally:
            config.vlm_model_name = saved
        self._install_graft()

    def _embed_owner(self) -> nn.Module:
        return self.model.vlm_with_expert

    def _lm_width(self) -> int:
        return self.model.vlm_with_expert.config.text_config.hidden_size

    def _embed_image(self, image: Tensor) -> Tensor:
        text = self.model.vlm_with_expert.get_vlm_model().text_model
        return self.graft.feed(image).to(text.get_input_embeddings().weight.dtype)

    def _bundled_assets(self) -> list[str]:
        name = self.config.vlm_model_name
        return [] if Path(name).is_absolute() else [name]

    def prepare_images(self, batch):
        self.graft.bind(batch)
        return super().prepare_images(batch)


class _GraftedPaliGemma(_Grafted):
    def _build(self, base_init, config, **kwargs) -> None:
        patches = contextlib.nullcontext()
        if config.tiny_arch:  # graftbench's tiny test world only: its construction patches
            from backbones.tiny_pi05 import TinyPI05Arch, tiny_pi05_patches

            arch = TinyPI05Arch.from_dict(json.loads(config.tiny_arch))
            patches = tiny_pi05_patches(arch, None, self.policy_type)
        with patches:
            base_init(self, config, **kwargs)
        self._install_graft()

    def _embed_owner(self) -> nn.Module:
        return self.model.paligemma_with_expert

    def _lm_width(self) -> int:
        return self.model.paligemma_with_expert.paligemma.config.text_config.hidden_size

    def _preprocess_images(self, batch):
        self.graft.bind(batch)
        return super()._preprocess_images(batch)


class GraftPI05Policy(_GraftedPaliGemma, PI05Policy):
    config_class = GraftPI05Config
    name = "graft_pi05"
    policy_type = "pi05"

    def __init__(self, config: GraftPI05Config, **kwargs):
        self._build(PI05Policy.__init__, config, **kwargs)


class GraftPI0Policy(_GraftedPaliGemma, PI0Policy):
    config_class = GraftPI0Config
    name = "graft_pi0"
    policy_type = "pi0"

    def __init__(self, config: GraftPI0Config, **kwargs):
        self._build(PI0Policy.__init__, config, **kwargs)
