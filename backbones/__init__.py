"""Backbone registry: adding a backbone is one entry (a module with the adapter functions).

Each module offers: INFO_REAL, build_tiny_policy(stats, camera_keys, ...), load_policy(path_or_repo,
stats=None), save_pretrained(backbone, folder), check_real_shapes().
"""

from __future__ import annotations

import difflib
import importlib
from dataclasses import dataclass
from types import ModuleType


@dataclass(frozen=True)
class BackboneEntry:
    name: str
    module: str  # import path of the adapter module
    repo_id: str  # the released checkpoint in the real world
    description: str


BACKBONES: dict[str, BackboneEntry] = {}


def register(entry: BackboneEntry) -> None:
    if entry.name in BACKBONES:
        raise ValueError(f"backbone {entry.name!r} registered twice")
    BACKBONES[entry.name] = entry


register(BackboneEntry("smolvla", "backbones.smolvla", "lerobot/smolvla_base",
                       "SmolVLA-450M (SmolVLM2 LM, width 960, 64 image tokens per camera)"))
register(BackboneEntry("pi05", "backbones.pi05", "lerobot/pi05_base",
                       "pi0.5-3.3B (PaliGemma/Gemma-2B, width 2048, 256 image tokens per camera)"))


def get_entry(name: str) -> BackboneEntry:
    if name not in BACKBONES:
        close = difflib.get_close_matches(name, BACKBONES, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"unknown backbone {name!r}{hint}; valid backbones: {', '.join(BACKBONES)}"
        )
    return BACKBONES[name]


def adapter_module(name: str) -> ModuleType:
    return importlib.import_module(get_entry(name).module)
