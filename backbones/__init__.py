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
    # Hub commit the paper profile loads (None: whatever the cache's main is; the record still
    # carries the resolved sha).
    revision: str | None = None
    # Whose normalisation stats: "dataset" (the suite's training episodes, as LeRobot's
    # fine-tuning does; base releases, whose saved stats are not LIBERO's) or "checkpoint" (the
    # release's own saved stats: LIBERO-trained releases, which must keep the normaliser they
    # were trained with).
    stats: str = "dataset"
    # Is this the study's choice (base releases) or an option beside it.
    study: bool = True
    # Parameters of the real release: the report orders backbones small to large by it.
    params: float = float("inf")

    def __post_init__(self) -> None:
        if self.stats not in ("dataset", "checkpoint"):
            raise ValueError(f"backbone {self.name!r}: stats={self.stats!r}, not 'dataset' or 'checkpoint'")


BACKBONES: dict[str, BackboneEntry] = {}


def register(entry: BackboneEntry) -> None:
    if entry.name in BACKBONES:
        raise ValueError(f"backbone {entry.name!r} registered twice")
    BACKBONES[entry.name] = entry


# Revisions: docs/HUB_FACTS.md (the commit most projects pin / the main seen, 2026).
register(BackboneEntry("smolvla", "backbones.smolvla", "lerobot/smolvla_base",
                       "SmolVLA-450M (SmolVLM2 LM, width 960, 64 image tokens per camera)",
                       revision="c83c3163b8ca9b7e67c509fffd9121e66cb96205", params=450e6))
register(BackboneEntry("pi05", "backbones.pi05", "lerobot/pi05_base",
                       "pi0.5-3.3B (PaliGemma/Gemma-2B, width 2048, 256 image tokens per camera)",
                       revision="b211f3d44c36b6acfcf7ae94a64e8e96f75a64ba", params=3.3e9))
# pi0: PaliGemma like pi0.5, the state a continuous token (an option beside the study's two).
register(BackboneEntry("pi0", "backbones.pi0", "lerobot/pi0_base",
                       "pi0-3.5B (PaliGemma/Gemma-2B, width 2048, 256 image tokens per camera, "
                       "continuous state token)",
                       revision="25c379b52ba2ff8788cab921758a3cc3fe3f77f2", study=False,
                       params=3.5e9))
# LIBERO-trained releases: a native reference that acts on LIBERO (not the study's choice).
register(BackboneEntry("smolvla_libero", "backbones.smolvla", "HuggingFaceVLA/smolvla_libero",
                       "SmolVLA-450M fine-tuned on LIBERO (its own saved stats)",
                       revision="6721902bc4d61e50a3bfdb11dfb4cb626f05d102", stats="checkpoint",
                       study=False, params=450e6))
register(BackboneEntry("pi05_libero", "backbones.pi05", "lerobot/pi05_libero_finetuned",
                       "pi0.5-3.3B fine-tuned on LIBERO (its own saved stats)",
                       revision="dbf8a3f794a9c4297b44f40b752712f50073d945", stats="checkpoint",
                       study=False, params=3.3e9))


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


def adapter_for_policy_type(policy_type: str) -> ModuleType:
    """The adapter module for a LeRobot config `type` ("smolvla", "pi05", "pi0"): the module of
    the registry's entries whose module name is that type. A checkpoint of your own is loaded by
    it (`--policy NAME=PATH`)."""
    modules = sorted({e.module for e in BACKBONES.values()})
    for module in modules:
        if module.rsplit(".", 1)[-1] == policy_type:
            return importlib.import_module(module)
    types = [m.rsplit(".", 1)[-1] for m in modules]
    raise ValueError(f"policy type {policy_type!r} has no graftbench adapter; adapters exist for "
                     f"{', '.join(types)} (docs/EXTENDING.md: a backbone)")
