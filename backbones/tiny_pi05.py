"""Construction-time patches that let LeRobot 0.6.1 build a REAL but tiny PI05Policy offline.

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
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

LEROBOT_PIN = "0.6.1"
TOKENIZER_DIRNAME = "tiny_paligemma_tokenizer"


def require_pinned_lerobot() -> None:
    """Raise unless lerobot is exactly the version these patches were written against."""
    import lerobot

    if lerobot.__version__ != LEROBOT_PIN:
        raise RuntimeError(
            f"backbones.tiny_pi05 patches are pinned to lerobot=={LEROBOT_PIN} (line references in "
            f"its docstring), found lerobot=={lerobot.__version__}: install lerobot=={LEROBOT_PIN} "
            "or re-check the patched lines and bump LEROBOT_PIN"
        )


@dataclass(frozen=True)
class TinyPI05Arch:
    """Sizes of the tiny pi0.5 (saved next to a checkpoint so loading rebuilds the same shapes)."""

    vlm_width: int = 64
    vlm_mlp_dim: int = 128
    expert_width: int = 32
    expert_mlp_dim: int = 64
    depth: int = 2  # VLM and expert layers are zipped pairwise (modeling_pi05.py:346): same depth
    num_heads: int = 8  # hard-coded 8 in modeling_pi05.py:121
    num_kv_heads: int = 1
    head_dim: int = 8
    vision_width: int = 32
    vision_layers: int = 2
    vision_heads: int = 2
    vision_mlp_dim: int = 64
    patch_size: int = 16
    vocab_size: int = 512  # >= the tiny tokenizer's size
    expert_vocab_size: int = 8

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> "TinyPI05Arch":
        return cls(**values)


# LeRobot policies built on the patched lines (lerobot.policies.<type>.modeling_<type>).
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
def tiny_gemma_variants(arch: TinyPI05Arch, policy_type: str = "pi05") -> Iterator[None]:
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
def tiny_paligemma(arch: TinyPI05Arch, policy_type: str = "pi05") -> Iterator[None]:
    """Shrink SigLIP, its projection (-> the tiny text width) and the vocab before PaliGemma is built."""
    m = _lerobot_module(policy_type, "modeling")

    real_cls = m.PaliGemmaForConditionalGenerationWithPiGemma

    @functools.wraps(real_cls)
    def build_tiny(config):
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
        return real_cls(config=config)

    with _swapped(m, "PaliGemmaForConditionalGenerationWithPiGemma", build_tiny):
        yield


@contextlib.contextmanager
def tiny_expert_vocab(arch: TinyPI05Arch, policy_type: str = "pi05") -> Iterator[None]:
    """The action expert's (unused) output vocabulary: arch.expert_vocab_size rows, not 257152."""
    m = _lerobot_module(policy_type, "modeling")

    real_cls = m.PiGemmaForCausalLM

    @functools.wraps(real_cls)
    def build_tiny(config):
        config.vocab_size = arch.expert_vocab_size
        return real_cls(config=config)

    with _swapped(m, "PiGemmaForCausalLM", build_tiny):
        yield


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
def tiny_pi05_patches(arch: TinyPI05Arch, tokenizer_dir: str | os.PathLike | None = None,
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


# -- the local tokenizer ------------------------------------------------------------------------
# Gemma's special ids: pad 0, eos 1, bos 2, unk 3 (GemmaConfig defaults).
_SPECIALS = ("<pad>", "<eos>", "<bos>", "<unk>")
# Punctuation of pi0.5's prompt "Task: {task}, State: {bins};\nAction: " (processor_pi05.py:74);
# "-" covers the bin -1 that np.digitize gives for states below -1 (:68).
_PUNCTUATION = (":", ",", ";", "-", ".", "'", "/")
_PROMPT_WORDS = ("task", "state", "action")
# Words of LIBERO task strings (spatial, object, goal, 10) and of the synthetic suites.
_TASK_WORDS = """
a and back basket bbq between black block blue book both bottle bottom bowl box butter cabinet caddy
center chocolate close compartment cookie cream cheese cube drawer dressing front from green in inside
it juice ketchup left middle microwave milk moka mug next of on open orange pick place plate pot pots
pudding push put rack ramekin red right salad sauce soup stove table the to tomato top turn up white
wine wooden yellow alphabet bin cup drawer lid move object onto over shelf side under yellow
""".split()


def tiny_vocabulary() -> list[str]:
    """Token strings of the tiny tokenizer, id order; includes every state bin 0..255."""
    words = [w for w in dict.fromkeys(_TASK_WORDS) if w not in _PROMPT_WORDS]
    numbers = [str(i) for i in range(256)]
    return [*_SPECIALS, *_PUNCTUATION, *_PROMPT_WORDS, *numbers, *words]


def _tokenizer_files() -> dict[str, str]:
    """The tokenizer folder's files as text (deterministic, so a cached copy can be compared)."""
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers, processors
    from transformers import PreTrainedTokenizerFast

    vocab = {token: i for i, token in enumerate(tiny_vocabulary())}
    tokenizer = Tokenizer(models.WordLevel(vocab=vocab, unk_token="<unk>"))
    tokenizer.normalizer = normalizers.Lowercase()
    tokenizer.pre_tokenizer = pre_tokenizers.Whitespace()  # splits "State:" and "12;" at punctuation
    # PaliGemma prepends <bos>; keep that so the prompt layout matches the real tokenizer's.
    tokenizer.post_processor = processors.TemplateProcessing(
        single="<bos> $A", special_tokens=[("<bos>", vocab["<bos>"])]
    )
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tokenizer,
        pad_token="<pad>",
        eos_token="<eos>",
        bos_token="<bos>",
        unk_token="<unk>",
    )
    with tempfile.TemporaryDirectory() as tmp:
        fast.save_pretrained(tmp)
        return {name: Path(tmp, name).read_text() for name in sorted(os.listdir(tmp))}


def ensure_tiny_tokenizer(folder: str | os.PathLike) -> Path:
    """Write the tiny tokenizer as a PreTrainedTokenizerFast folder (atomic; reused when equal)."""
    folder = Path(folder)
    files = _tokenizer_files()
    if folder.is_dir() and all(
        (folder / name).is_file() and (folder / name).read_text() == text for name, text in files.items()
    ):
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=folder.name + ".", dir=folder.parent))
    for name, text in files.items():
        (staging / name).write_text(text)
    stale = folder.with_name(folder.name + f".stale-{os.getpid()}")
    if folder.exists():
        folder.rename(stale)
    try:
        staging.rename(folder)
    except OSError:  # another process won the race with identical content
        shutil.rmtree(staging, ignore_errors=True)
    shutil.rmtree(stale, ignore_errors=True)
    return folder

