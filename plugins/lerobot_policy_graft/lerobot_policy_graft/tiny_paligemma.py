"""Construction-time patches that let LeRobot 0.6.1 build a REAL but tiny PI05Policy offline.

graftbench builds its tiny pi0 / pi0.5 under them (backbones.tiny_paligemma, which adds the local
tokenizer); they live in the plugin because a tiny graft exported from graftbench's offline test
world is rebuilt under them too, where graftbench is not installed.

LeRobot's pi0.5 hard-codes the PaliGemma-3B/Gemma-300M sizes and the hub tokenizer. Four narrow
patches, each a context manager that swaps one module-level name and restores it on exit, stand in
for exactly those lines (lerobot/policies/pi05/, lerobot 0.6.1):

1. `tiny_gemma_variants`  modeling_pi05.py:158-179 `get_gemma_config` (only gemma_300m/gemma_2b
   exist, and configuration_pi05.py:115-119 rejects other names): the config keeps the real names,
   "gemma_2b" -> the tiny VLM and "gemma_300m" -> the tiny expert. 8 heads are kept because
   modeling_pi05.py:121 reshapes attention to `1 * 8 * head_dim`; heads, kv heads and head_dim are
   the same in both (their q/k/v are concatenated in one attention, :93-95).
2. `tiny_paligemma`       modeling_pi05.py:203-221,237: vocab 257152, SigLIP-So400m (1152 wide,
   27 layers, intermediate 4304) and projection 2048 are assigned after the config is built, so we
   wrap the PaliGemma constructor called at :237 and shrink its config just before construction.
3. `tiny_expert_vocab`    modeling_pi05.py:230,238: the expert's vocab is 257152 too; its output
   layer is never used but would hold most of the tiny model's parameters.
4. `local_tokenizer`      processor_pi05.py:140-145: `TokenizerProcessorStep("google/paligemma-
   3b-pt-224")`, the only hub access when building; we point it at a local WordLevel tokenizer.

Nothing here touches the forward pass: the built model runs LeRobot's own code unchanged.

pi0 (lerobot/policies/pi0/) is built from the same lines under the same names, so every patch
takes `policy_type` ("pi05" or "pi0"): modeling_pi0.py:161-182 `get_gemma_config`, :124 the 8
heads, :203-222,240 PaliGemma sizes and constructor, :233,241 the expert vocab, and
processor_pi0.py:140-145 the tokenizer step. pi0's own extra layer, `state_proj`
(Linear(max_state_dim -> expert width), :433), needs no patch.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib
import json
import os
from dataclasses import dataclass
from typing import Any, Iterator


LEROBOT_PIN = "0.6.1"


def require_pinned_lerobot() -> None:
    """Raise unless lerobot is exactly the version these patches were written against."""
    import lerobot

    if lerobot.__version__ != LEROBOT_PIN:
        raise RuntimeError(
            f"the tiny PaliGemma patches are pinned to lerobot=={LEROBOT_PIN} (line references in "
            f"its docstring), found lerobot=={lerobot.__version__}: install lerobot=={LEROBOT_PIN} "
            "or re-check the patched lines and bump LEROBOT_PIN"
        )


@dataclass(frozen=True)
class TinyPaliGemmaArch:
    """Sizes of the tiny pi0.5 (saved next to a checkpoint so loading rebuilds the same shapes)."""

    # Gemma: the VLM and the action expert, zipped pairwise layer by layer (modeling_pi05.py:346),
    # so of one depth; heads, kv heads and head_dim shared (their q/k/v meet in one attention).
    vlm_width: int = 64
    vlm_mlp_dim: int = 128
    expert_width: int = 32
    expert_mlp_dim: int = 64
    depth: int = 2
    """Attention, shared by the VLM and the expert: 8 heads are hard-coded (modeling_pi05.py:121)."""
    num_heads: int = 8
    num_kv_heads: int = 1
    head_dim: int = 8
    """SigLIP, the vision tower: a 64 px image is a 4x4 patch grid."""
    vision_width: int = 32
    vision_layers: int = 2
    vision_heads: int = 2
    vision_mlp_dim: int = 64
    patch_size: int = 16
    """Vocabularies: the VLM's covers the tiny tokenizer; the expert's output layer is unused."""
    vocab_size: int = 512
    expert_vocab_size: int = 8

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "TinyPaliGemmaArch":
        return cls(**values)

    @classmethod
    def from_json(cls, text: str) -> "TinyPaliGemmaArch":
        """From a graft config's `tiny_arch` (JSON of `to_dict`)."""
        return cls(**json.loads(text))


# LeRobot policies built on the patched lines (lerobot.policies.<type>.modeling_<type>): the
# PaliGemma families of families.py, spelled here because families.py imports this module (when
# a config asks for the tiny arch); tests/test_structure.py checks the two agree.
POLICY_TYPES = ("pi05", "pi0")


def _lerobot_module(policy_type: str, kind: str) -> Any:
    """lerobot.policies.<policy_type>.<kind>_<policy_type> (kind: "modeling" or "processor")."""
    if policy_type not in POLICY_TYPES:
        raise ValueError(f"policy_type {policy_type!r}: the tiny patches know {list(POLICY_TYPES)}")
    return importlib.import_module(f"lerobot.policies.{policy_type}.{kind}_{policy_type}")


@contextlib.contextmanager
def _swapped(module: Any, name: str, replacement: Any) -> Iterator[None]:
    """Set `module.name = replacement` inside the block; restore the original on exit."""
    original = getattr(module, name)
    setattr(module, name, replacement)
    try:
        yield
    finally:
        setattr(module, name, original)


@contextlib.contextmanager
def tiny_gemma_variants(arch: TinyPaliGemmaArch, policy_type: str = "pi05") -> Iterator[None]:
    """modeling_pi05.get_gemma_config: "gemma_2b" -> tiny VLM, "gemma_300m" -> tiny expert."""
    m = _lerobot_module(policy_type, "modeling")

    sizes = {
        "gemma_2b": (arch.vlm_width, arch.vlm_mlp_dim),
        "gemma_300m": (arch.expert_width, arch.expert_mlp_dim),
    }

    def get_tiny_gemma_config(variant: str):
        if variant not in sizes:
            raise ValueError(f"Unknown variant: {variant}; the tiny build knows {sorted(sizes)}")
        width, mlp_dim = sizes[variant]
        return m.GemmaConfig(
            width=width,
            depth=arch.depth,
            mlp_dim=mlp_dim,
            num_heads=arch.num_heads,
            num_kv_heads=arch.num_kv_heads,
            head_dim=arch.head_dim,
        )

    with _swapped(m, "get_gemma_config", get_tiny_gemma_config):
        yield


@contextlib.contextmanager
def _shrunk(module: Any, name: str, shrink) -> Iterator[None]:
    """Inside the block, `module.name` (a class built from a config) builds from the config as
    `shrink(config)` leaves it."""
    real_cls = getattr(module, name)

    @functools.wraps(real_cls)
    def build_tiny(config):
        shrink(config)
        return real_cls(config=config)

    with _swapped(module, name, build_tiny):
        yield


def tiny_paligemma(arch: TinyPaliGemmaArch, policy_type: str = "pi05"):
    """Shrink SigLIP, its projection (-> the tiny text width) and the vocab before PaliGemma is built."""
    def shrink(config) -> None:
        vision = config.vision_config  # image_size was set from config.image_resolution (:217)
        if vision.image_size % arch.patch_size:
            raise ValueError(
                f"image size {vision.image_size} is not a multiple of the tiny patch {arch.patch_size}"
            )
        vision.hidden_size = arch.vision_width
        vision.num_hidden_layers = arch.vision_layers
        vision.num_attention_heads = arch.vision_heads
        vision.intermediate_size = arch.vision_mlp_dim
        vision.patch_size = arch.patch_size
        vision.projection_dim = config.text_config.hidden_size
        config.projection_dim = config.text_config.hidden_size
        config.text_config.num_image_tokens = (vision.image_size // arch.patch_size) ** 2
        config.text_config.vocab_size = arch.vocab_size
        config.vocab_size = arch.vocab_size
        config.image_token_index = arch.vocab_size - 1  # unused by pi0.5 (no input_ids path)

    return _shrunk(_lerobot_module(policy_type, "modeling"),
                   "PaliGemmaForConditionalGenerationWithPiGemma", shrink)


def tiny_expert_vocab(arch: TinyPaliGemmaArch, policy_type: str = "pi05"):
    """The action expert's (unused) output vocabulary: arch.expert_vocab_size rows, not 257152."""
    def shrink(config) -> None:
        config.vocab_size = arch.expert_vocab_size

    return _shrunk(_lerobot_module(policy_type, "modeling"), "PiGemmaForCausalLM", shrink)


@contextlib.contextmanager
def local_tokenizer(tokenizer_dir: str | os.PathLike, policy_type: str = "pi05") -> Iterator[None]:
    """processor_<type>'s TokenizerProcessorStep loads `tokenizer_dir` instead of the hub tokenizer."""
    p = _lerobot_module(policy_type, "processor")

    real_cls = p.TokenizerProcessorStep

    @functools.wraps(real_cls)
    def build_local(**kwargs):
        kwargs["tokenizer_name"] = str(tokenizer_dir)
        return real_cls(**kwargs)

    with _swapped(p, "TokenizerProcessorStep", build_local):
        yield


@contextlib.contextmanager
def tiny_paligemma_patches(arch: TinyPaliGemmaArch, tokenizer_dir: str | os.PathLike | None = None,
                      policy_type: str = "pi05"):
    """All construction patches at once (tokenizer only when `tokenizer_dir` is given), for
    LeRobot's `policy_type` ("pi05", or "pi0", built from the same lines)."""
    require_pinned_lerobot()
    with contextlib.ExitStack() as stack:
        stack.enter_context(tiny_gemma_variants(arch, policy_type))
        stack.enter_context(tiny_paligemma(arch, policy_type))
        stack.enter_context(tiny_expert_vocab(arch, policy_type))
        if tokenizer_dir is not None:
            stack.enter_context(local_tokenizer(tokenizer_dir, policy_type))
        yield
