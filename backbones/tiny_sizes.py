"""The tiny size ladder: each backbone family at several sizes, one table entry per size.

The study's two backbones differ in family and in size at once (SmolVLA-450M, pi0.5-3.3B). In the
tiny world both families are LeRobot's real classes at sizes we choose, so a family can be built
at several sizes and trained natively by one recipe on the same scenes: a size is then a
backbone of its own (a registry name, e.g. `smolvla_m`), with its own releases and cells.

What a size scales: the language model and the action expert (width w, depth L), the part a graft
keeps frozen. What stays: what the family is, i.e. its vision tower (the same 32-wide, 2-layer
SigLIP-shaped tower in both families; a graft replaces it), its image token grid (SmolVLA 2x2 per
camera after the pixel shuffle, pi0.5 4x4, the real releases' 8x8 and 16x16 at a quarter of the
side), its prompt and state input, its time conditioning. Real families grow the same way:
SmolVLM-256M and -500M, PaliGemma-3B and -10B keep their tower and scale the language model.

Matched across families by construction, rung by rung (s, m, l): the same w, L, MLP width 2w,
attention projections (queries w wide, keys and values w/2: SmolVLA's w/16 heads of 16 with half
as many key-value heads, pi0.5's 8 heads of w/8 with 4 key-value heads, 8 heads being hard-coded
in LeRobot's pi0.5), action expert 0.75 w wide with SmolVLA's own expert MLP rule
(lerobot smolvlm_with_expert.get_intermediate_size), the same vision tower. Parameters cannot be
matched as well: what differs is the family itself (pi0.5's adaptive-RMSNorm time conditioning in
the expert, its 384-word vocabulary holding the state bins, an untied output layer), so pi0.5
holds 1.21-1.22x SmolVLA's parameters at every rung; `matched_pairs` lists the pairs and the
report quotes both counts. Rung xs is today's tiny pi0.5 (depth 2, expert 32 wide, 1 key-value
head), kept as it is so its releases and records resume; it has no SmolVLA twin. Today's tiny
SmolVLA (w 64, L 4) is rung s exactly (tests/test_tiny_sizes.py builds `smolvla_arch(64, 4)` and
finds the same weights).

`params` is the build's parameter count with the recipe's inputs (two 64 px cameras, an 8-dim
state, 7-dim actions, chunk 10): all of them train natively (bench.resources.releases), checked
by tests/test_tiny_sizes.py. `step_s` is one native training step at the recipe's batch (16),
one torch thread, the median CPU seconds of 6 steps (the least disturbed figure on a shared
machine; studies/family_scale/README.md has the measurement): the native recipe's 1,500 steps then
take 1,500 x step_s, and l is the largest whose pi0.5 trains in about 30 minutes (26 min).

Plain data (no torch): the registry (backbones/__init__.py) registers one entry per size here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

# Smallest first; sizes matched across families share a rung.
RUNGS = ("xs", "s", "m", "l")


def smolvla_arch(width: int, depth: int) -> dict[str, Any]:
    """The tiny SmolVLA's numbers at LM width `width` and `depth` layers (backbones.tiny_smolvla
    sized_vlm keys); its expert is 0.75 x width by SmolVLAConfig's default."""
    heads = width // 16
    return {"text.hidden_size": width, "text.intermediate_size": 2 * width,
            "text.num_hidden_layers": depth, "text.num_attention_heads": heads,
            "text.num_key_value_heads": heads // 2, "text.head_dim": 16}


def smolvla_expert_mlp(expert_width: int) -> int:
    """SmolVLA's expert MLP width for an expert `expert_width` wide (lerobot 0.6.1
    smolvlm_with_expert.get_intermediate_size: 4 x 2/3 x width, up to a multiple of 256)."""
    return 256 * -(-(int(2 * expert_width / 3) * 4) // 256)


def pi05_arch(width: int, depth: int) -> dict[str, Any]:
    """The tiny pi0.5's numbers (TinyPaliGemmaArch fields) matched to smolvla_arch(width, depth)."""
    expert = int(0.75 * width)
    return {"vlm_width": width, "vlm_mlp_dim": 2 * width, "expert_width": expert,
            "expert_mlp_dim": smolvla_expert_mlp(expert), "depth": depth, "num_kv_heads": 4,
            "head_dim": width // 8}


@dataclass(frozen=True)
class TinySize:
    """One size of a family's tiny ladder: its registry name, the study backbone of its family,
    its rung, its parameter count, one native step's CPU seconds, and the architecture numbers
    that differ from the family's base tiny build ({}: the base build itself)."""

    name: str
    family: str
    rung: str
    params: int
    step_s: float
    arch: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.rung not in RUNGS:
            raise ValueError(f"tiny size {self.name!r}: rung {self.rung!r}, not one of {RUNGS}")

    @property
    def base(self) -> bool:
        """The family's own tiny build (its release 0 keys and records are today's)."""
        return not self.arch

    @property
    def native_minutes(self) -> float:
        """Minutes of one thread for the native recipe's 1,500 steps (step_s measured)."""
        return 1500 * self.step_s / 60


SIZES: dict[str, TinySize] = {}


def _add(size: TinySize) -> None:
    if size.name in SIZES:
        raise ValueError(f"tiny size {size.name!r} listed twice")
    if any(s.family == size.family and s.rung == size.rung for s in SIZES.values()):
        raise ValueError(f"tiny size {size.name!r}: {size.family} already has rung {size.rung}")
    SIZES[size.name] = size


# One entry per size. step_s: studies/family_scale/README.md ("The ladder").
_add(TinySize("pi05", "pi05", "xs", 203_264, 0.070))
_add(TinySize("smolvla", "smolvla", "s", 409_728, 0.062))  # = smolvla_arch(64, 4)
_add(TinySize("pi05_s", "pi05", "s", 497_632, 0.133, pi05_arch(64, 4)))
_add(TinySize("smolvla_m", "smolvla", "m", 2_978_304, 0.163, smolvla_arch(160, 6)))
_add(TinySize("pi05_m", "pi05", "m", 3_610_544, 0.349, pi05_arch(160, 6)))
_add(TinySize("smolvla_l", "smolvla", "l", 13_910_784, 0.536, smolvla_arch(320, 8)))
_add(TinySize("pi05_l", "pi05", "l", 17_026_784, 1.039, pi05_arch(320, 8)))


def size_of(name: str) -> TinySize | None:
    """The ladder entry of backbone `name`; None for a backbone outside the ladder."""
    return SIZES.get(name)


def ladder(family: str) -> list[TinySize]:
    """The sizes of `family` (a study backbone's name), smallest first."""
    return sorted((s for s in SIZES.values() if s.family == family),
                  key=lambda s: RUNGS.index(s.rung))


def matched_pairs() -> list[tuple[TinySize, TinySize]]:
    """(SmolVLA size, pi0.5 size) of every rung both families have, smallest first."""
    by_rung: dict[str, dict[str, TinySize]] = {}
    for s in SIZES.values():
        by_rung.setdefault(s.rung, {})[s.family] = s
    families = sorted({s.family for s in SIZES.values()}, key=lambda f: f != "smolvla")
    return [tuple(by_rung[r][f] for f in families) for r in RUNGS
            if r in by_rung and len(by_rung[r]) == len(families)]


def build_args(name: str) -> dict[str, Any]:
    """What the adapter's build_tiny_policy takes for backbone `name` beside its base arguments:
    {"arch": ...} for a size of the ladder, {} for a family's base build or a backbone outside
    the ladder (so their builds, keys and records stay as they were)."""
    size = SIZES.get(name)
    return {"arch": dict(size.arch)} if size is not None and not size.base else {}
