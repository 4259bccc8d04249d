"""Backbone registry: adding a backbone is one entry (a module with the adapter functions).

Each entry names its LeRobot policy type and its adapter module; the module offers what
backbones.seam.AdapterModule lists (INFO_REAL, BACKBONE_CLASS, RENAMES_CAMERAS,
build_tiny_policy, load_policy, save_pretrained, check_real_shapes, artifacts,
write_hub_release), checked when `adapter_module` first loads it.
"""

from __future__ import annotations

import difflib
import functools
import importlib
from dataclasses import dataclass

from backbones.seam import AdapterModule, check_adapter
from backbones.tiny_sizes import SIZES as TINY_SIZES


@dataclass(frozen=True)
class BackboneEntry:
    name: str
    policy_type: str  # the LeRobot config `type` the adapter loads ("smolvla", "pi05", "pi0")
    module: str  # import path of the adapter module (backbones.seam.AdapterModule)
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
    # Parameters of the real release: the report orders backbones small to large by it (a
    # size of the tiny ladder: its family's, then the ladder's rung).
    params: float = float("inf")
    # A size of the tiny ladder (backbones.tiny_sizes) that exists only in the tiny world: its
    # rung; no hub release (repo_id ""), so a hub profile refuses it at start-up.
    tiny_size: str | None = None

    def __post_init__(self) -> None:
        if self.stats not in ("dataset", "checkpoint"):
            raise ValueError(f"backbone {self.name!r}: stats={self.stats!r}, not 'dataset' or 'checkpoint'")
        if (self.tiny_size is None) == (not self.repo_id):
            raise ValueError(f"backbone {self.name!r}: a hub release needs a repo_id, a tiny-only "
                             f"size none (repo_id={self.repo_id!r}, tiny_size={self.tiny_size!r})")

    @property
    def on_hub(self) -> bool:
        """Has a release on the hub (else: a size of the tiny ladder, the tiny world only)."""
        return self.tiny_size is None


BACKBONES: dict[str, BackboneEntry] = {}


def register(entry: BackboneEntry) -> None:
    if entry.name in BACKBONES:
        raise ValueError(f"backbone {entry.name!r} registered twice")
    BACKBONES[entry.name] = entry


# Revisions: docs/HUB_FACTS.md (the commit most projects pin / the main seen, 2026).
register(BackboneEntry("smolvla", "smolvla", "backbones.smolvla", "lerobot/smolvla_base",
                       "SmolVLA-450M (SmolVLM2 LM, width 960, 64 image tokens per camera)",
                       revision="c83c3163b8ca9b7e67c509fffd9121e66cb96205", params=450e6))
register(BackboneEntry("pi05", "pi05", "backbones.pi05", "lerobot/pi05_base",
                       "pi0.5-3.3B (PaliGemma/Gemma-2B, width 2048, 256 image tokens per camera)",
                       revision="b211f3d44c36b6acfcf7ae94a64e8e96f75a64ba", params=3.3e9))
# pi0: PaliGemma like pi0.5, the state a continuous token (an option beside the study's two).
register(BackboneEntry("pi0", "pi0", "backbones.pi0", "lerobot/pi0_base",
                       "pi0-3.5B (PaliGemma/Gemma-2B, width 2048, 256 image tokens per camera, "
                       "continuous state token)",
                       revision="25c379b52ba2ff8788cab921758a3cc3fe3f77f2", study=False,
                       params=3.5e9))
# LIBERO-trained releases: a native reference that acts on LIBERO (not the study's choice).
register(BackboneEntry("smolvla_libero", "smolvla", "backbones.smolvla", "HuggingFaceVLA/smolvla_libero",
                       "SmolVLA-450M fine-tuned on LIBERO (its own saved stats)",
                       revision="6721902bc4d61e50a3bfdb11dfb4cb626f05d102", stats="checkpoint",
                       study=False, params=450e6))
register(BackboneEntry("pi05_libero", "pi05", "backbones.pi05", "lerobot/pi05_libero_finetuned",
                       "pi0.5-3.3B fine-tuned on LIBERO (its own saved stats)",
                       revision="dbf8a3f794a9c4297b44f40b752712f50073d945", stats="checkpoint",
                       study=False, params=3.3e9))


# The tiny ladder's other sizes (backbones.tiny_sizes), each with its family's adapter, after the
# real releases so that a policy type's first entry stays its study backbone.
for _size in TINY_SIZES.values():
    if _size.name not in BACKBONES:
        _family = BACKBONES[_size.family]
        register(BackboneEntry(
            _size.name, _family.policy_type, _family.module, "",
            f"tiny {_family.name} at size {_size.rung} ({_size.params:,} parameters; "
            "the tiny world only)", study=False, params=_family.params, tiny_size=_size.rung))


def get_entry(name: str) -> BackboneEntry:
    """The entry of backbone `name`; else ValueError in bench.table's one refusal shape (this
    registry sits below bench: it cannot import it)."""
    if name not in BACKBONES:
        # The name in other case first (smolvla_L); a ladder size is a suggestion only where
        # no family's own name is close.
        close = ([n for n in BACKBONES if n.lower() == name.lower()]
                 or difflib.get_close_matches(name, [n for n, e in BACKBONES.items()
                                                     if e.tiny_size is None], n=1)
                 or difflib.get_close_matches(name, BACKBONES, n=1))
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"unknown backbone {name!r}{hint}; valid backbones: {', '.join(BACKBONES)}"
        )
    return BACKBONES[name]


def adapter_module(name: str) -> AdapterModule:
    """The adapter module of backbone `name`, checked against the seam on first load."""
    return _load_adapter(get_entry(name).module, name)


@functools.lru_cache(maxsize=None)
def _load_adapter(module_path: str, backbone: str) -> AdapterModule:
    module = importlib.import_module(module_path)
    check_adapter(module, backbone)
    return module


def adapter_for_policy_type(policy_type: str) -> AdapterModule:
    """The adapter module for a LeRobot config `type` ("smolvla", "pi05", "pi0"): that of the
    registry's entries of that policy type. A checkpoint of your own is loaded by it
    (`--policy NAME=PATH`)."""
    for entry in BACKBONES.values():
        if entry.policy_type == policy_type:
            return adapter_module(entry.name)
    types = sorted({e.policy_type for e in BACKBONES.values()})
    raise ValueError(f"policy type {policy_type!r} has no graftbench adapter; adapters exist for "
                     f"{', '.join(types)} (docs/EXTENDING.md: a backbone)")


def study_backbone(name: str) -> str:
    """The study's backbone a backbone of ours belongs to: the study entry of its policy type
    ('pi05_libero' -> 'pi05'); itself when it has none (pi0, a --policy name)."""
    if name in BACKBONES:
        for entry in BACKBONES.values():
            if entry.study and entry.policy_type == BACKBONES[name].policy_type:
                return entry.name
    return name
