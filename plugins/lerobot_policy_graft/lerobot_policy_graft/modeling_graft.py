"""Grafted policies: LeRobot's own SmolVLAPolicy / PI05Policy / PI0Policy, with ONLY the image
embedding replaced: camera pixels in [0, 1] -> timm encoder (its own resize and mean/std) ->
grid pooled to the native token grid -> LayerNorm (no affine) -> Linear, the fixed wrapper
(`graftcore.graft`) that graftbench measures with, spliced in at the family's graft
point (`lerobot_policy_graft.families`).

Loading is strict (LeRobot's SmolVLA loads with strict=False and only logs; pi0 / pi0.5 print and
keep random weights): a missing or unexpected key raises. Folders a config names relative to the
checkpoint (the bundled tiny VLM) resolve against it, and are copied along when it is saved.
"""

from __future__ import annotations

import contextlib
import contextvars
import shutil
from pathlib import Path

import torch
from lerobot.configs import PreTrainedConfig
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor, nn

from lerobot_policy_graft.configuration_graft import (
    TRAIN_SCOPES, GraftPI0Config, GraftPI05Config, GraftSmolVLAConfig, config_from_pretrained,
)
from graftcore.encoder import encoder_from_config
from lerobot_policy_graft.families import PI0, PI05, SMOLVLA, GraftFamily
from graftcore.graft import GraftFeed, Projector, pool_grid

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


def _resolved(name: str) -> str:
    """A config's asset name, resolved against the checkpoint being loaded when it is there."""
    root = _ASSET_ROOT.get()
    if root is not None and not Path(name).is_absolute() and (root / name).is_dir():
        return str(root / name)
    return name


class GraftHead(nn.Module):
    """Encoder + projector; `bind(batch)` encodes the batch's cameras for the embed_image calls
    that follow (one per camera, in `camera_keys` order)."""

    def __init__(self, config, lm_width: int) -> None:
        super().__init__()
        self.encoder = encoder_from_config(config)
        self.projector = Projector(config.encoder_channels, lm_width)
        self.grid = (int(config.graft_grid[0]), int(config.graft_grid[1]))
        self.camera_keys = tuple(config.image_features)
        self.train_encoder = "graft.encoder." in (TRAIN_SCOPES[config.train_scope] or ())
        self.feed = GraftFeed(self.projector, self.camera_keys, self.grid)

    def encode(self, images: Tensor) -> Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, rows*cols, C) pooled, as graftbench's encode_pooled."""
        device = next(self.encoder.parameters()).device
        images = images.to(device, torch.float32)
        if self.train_encoder and torch.is_grad_enabled():  # the encoder's forward is no_grad
            grid = self.encoder.grid(images)
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
    """What every grafted policy is, its family's differences read from `family`: built under
    the family's construction context, the graft installed at its graft point, the batch's
    cameras encoded where the family prepares its images (`images_method`)."""

    family: GraftFamily
    config_class: type
    name: str

    def __init__(self, config, **kwargs):
        with self.family.building(config, _resolved):
            super().__init__(config, **kwargs)
        self.graft = GraftHead(config, self.family.lm_width(self))
        self.family.install(self, self.graft.feed)
        prefixes = TRAIN_SCOPES[config.train_scope]
        if prefixes is not None:
            for name, param in self.named_parameters():
                param.requires_grad_(name.startswith(prefixes))
        self._asset_root = _ASSET_ROOT.get()

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
        for name in self.family.bundled_assets(self.config):
            source = self._asset_root / name if self._asset_root else None
            target = Path(save_directory) / name
            if source is not None and source.is_dir() and source.resolve() != target.resolve():
                shutil.copytree(source, target, dirs_exist_ok=True)


def _local_folder(name_or_path, revision: str | None) -> Path:
    path = Path(name_or_path)
    if path.is_dir():
        return path
    from huggingface_hub import snapshot_download

    return Path(snapshot_download(str(name_or_path), revision=revision))


def grafted_policy(family: GraftFamily, config_class: type) -> type:
    """The grafted policy class of `family`: `_Grafted` over LeRobot's own policy class, named
    as LeRobot's convention looks it up (Graft<Prefix>Config -> Graft<Prefix>Policy here)."""
    base = family.lerobot_class("modeling", "Policy")
    prepare_images = getattr(base, family.images_method)

    def encode_then_prepare(self, batch, *args, **kwargs):
        self.graft.bind(batch)  # the batch's own pixels, for the embed_image calls that follow
        return prepare_images(self, batch, *args, **kwargs)

    name = config_class.__name__.removesuffix("Config") + "Policy"
    return type(name, (_Grafted, base), {
        "__module__": __name__, "__qualname__": name, "__doc__": f"{family.label}, grafted.",
        "family": family, "config_class": config_class, "name": f"graft_{family.policy_type}",
        family.images_method: encode_then_prepare})


GraftSmolVLAPolicy = grafted_policy(SMOLVLA, GraftSmolVLAConfig)
GraftPI05Policy = grafted_policy(PI05, GraftPI05Config)
GraftPI0Policy = grafted_policy(PI0, GraftPI0Config)
