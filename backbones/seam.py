"""The seam between the harness and a backbone family: what an adapter module offers.

Light to import (no torch): the registry (backbones/__init__.py) checks each entry's module
against `AdapterModule` when it first loads it; a missing member is one line naming it.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, Mapping, Protocol, Sequence

if TYPE_CHECKING:
    from backbones.base import Backbone, BackboneInfo
    from ondisk.artifacts import Artifact


class AdapterModule(Protocol):
    """What an adapter module (backbones/smolvla.py, pi05.py, pi0.py) offers the harness, and all
    the harness calls on it: `adapter_module` checks an entry's module against it on loading."""

    INFO_REAL: BackboneInfo  # the real release: token grid, LM width, chunk, action dims
    BACKBONE_CLASS: type[Backbone]  # the adapter class; its `image_embedder` is the graft point
    # load_policy also takes rename_map, camera_keys, state_dim, action_dim: a checkpoint of
    # your own (--policy) may be fed from dataset cameras of other names.
    RENAMES_CAMERAS: bool

    def build_tiny_policy(self, stats: dict, camera_keys: Sequence[str] = ...,
                          image_hw: tuple[int, int] = (64, 64), state_dim: int = ...,
                          action_dim: int = ..., chunk_size: int = 10, seed: int = 0, *,
                          arch: Mapping[str, Any] | None = None) -> Backbone:
        """A real LeRobot policy of the family at tiny sizes, offline, the same for a seed;
        `arch`: the numbers of another size of the tiny ladder (backbones.tiny_sizes)."""

    def load_policy(self, path_or_repo_id: str, stats: dict | None = None, *,
                    revision: str | None = None, device: str | None = None) -> Backbone:
        """A saved folder or a hub id in the HF cache; `stats` replace the saved ones."""

    def save_pretrained(self, backbone: Backbone, folder: str | os.PathLike) -> Path:
        """Everything `load_policy(folder)` needs to restore `backbone`."""

    def check_real_shapes(self) -> dict:
        """The real architecture built without weights; raises if it disagrees with INFO_REAL."""

    def artifacts(self, repo_id: str, revision: str | None, needed_by: str) -> list[Artifact]:
        """What loading `repo_id`@`revision` reads from the HF cache (the paper preflight)."""

    def write_hub_release(self, hub_cache: Path, repo_id: str, revision: str | None) -> None:
        """The base release `repo_id`@`revision` at tiny size, shaped as the hub's, into the HF
        cache folder `hub_cache` (the offline hub world, bench/offline_hub.py)."""


ADAPTER_MEMBERS = tuple(AdapterModule.__annotations__) + tuple(
    name for name, value in vars(AdapterModule).items()
    if callable(value) and not name.startswith("_"))


def check_adapter(module: ModuleType, backbone: str) -> None:
    """Raise one line naming every AdapterModule member `module` lacks."""
    missing = [m for m in ADAPTER_MEMBERS if not hasattr(module, m)]
    if missing:
        raise TypeError(f"backbone {backbone!r}: adapter module {module.__name__} lacks "
                        f"{', '.join(missing)} (the seam: backbones.seam.AdapterModule)")
