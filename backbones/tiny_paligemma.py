"""graftbench's tiny pi0 / pi0.5, built offline: LeRobot's own policy classes at tiny sizes.

The construction patches (tiny Gemma variants, SigLIP, expert vocabulary; line references to
lerobot 0.6.1 in their docstring) live in the plugin, `lerobot_policy_graft.tiny_paligemma`,
because a tiny graft exported from the offline test world is rebuilt under them where graftbench
is not installed; they are re-exported here for the adapters. What is graftbench's alone: the
local WordLevel tokenizer that stands in for google/paligemma-3b-pt-224 (the fourth patch,
`local_tokenizer`, points LeRobot's tokenizer step at it).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from lerobot_policy_graft.tiny_paligemma import (  # noqa: F401  (the adapters' import point)
    LEROBOT_PIN,
    POLICY_TYPES,
    TinyPaliGemmaArch,
    local_tokenizer,
    require_pinned_lerobot,
    tiny_expert_vocab,
    tiny_gemma_variants,
    tiny_paligemma,
    tiny_paligemma_patches,
)

TOKENIZER_DIRNAME = "tiny_paligemma_tokenizer"


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

