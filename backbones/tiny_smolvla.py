"""SmolVLA built with no network: local SmolVLM folders and the configs that point at them.

SmolVLA reads its VLM's config, processor and tokenizer by name (AutoConfig / AutoProcessor in
lerobot/policies/smolvla/smolvlm_with_expert.py ~99-101, AutoTokenizer in processor_smolvla.py
~69-74). Pointing `vlm_model_name` at a folder holding the four files below (config.json,
processor_config.json, tokenizer.json, tokenizer_config.json) builds it fully offline.

Two folders are made here:
- `tiny_vlm_folder()`: a tiny SmolVLM (vision 32 wide, 64 px, patch 16, pixel shuffle 2 -> 2x2 = 4
  tokens per camera; llama text 64 wide, 4 layers) used by the offline world and CI.
- `real_shape_vlm_folder()`: the SmolVLM2-500M architecture numbers (no weights), used to check
  the real backbone's token grid and LM width without downloading anything.
Both use a small word-level tokenizer covering the words of LIBERO task strings.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Mapping

import torch

from ondisk.paths import cache_dir
from ondisk.libero_format import (
    ACTION_KEY, IMAGE_KEYS, LIBERO_ACTION_DIM, LIBERO_STATE_DIM, STATE_KEY,
)

# Bump when the folder contents change in a way the spec hash below does not see.
FOLDER_FORMAT = "1"

# Words of the LIBERO task strings (Spatial, Object, Goal, 10) and of the synthetic suites'
# (bench/suites/synthetic.py). Anything else becomes [UNK]; text is lowercased and punctuation
# split off ("counter-clockwise" -> counter - clockwise).
TASK_WORDS = """
a above akita all alphabet and apple around at back basket bbq behind below beside between black
block blue book both bottle bottom bowl box butter cabinet caddy center cheese chocolate clockwise
close compartment cookie counter cream cross cup desk disk drawer dressing flat from front frying
green gripper in inside into it its juice ketchup left match matching microwave middle milk moka
mug mugs next object of off on one onto open opposite orange pan pick place plate porcelain pot
pots pudding push put rack ramekin red right salad sauce shelf square stack step stove table the
to tomato top towards tray triangle turn up white wine wooden yellow
""".split()
PUNCTUATION = list(".,;:!?'\"-()")
SPECIAL_TOKENS = {
    "pad": "[PAD]",
    "unk": "[UNK]",
    # SmolVLA's model asks the tokenizer for these (modeling_smolvla.py, VLAFlowMatching.__init__).
    "fake_image_token": "<fake_token_around_image>",
    "image_token": "<image>",
    "global_image_token": "<global-img>",
    "end_of_utterance_token": "<end_of_utterance>",
}

# SmolVLM architecture numbers. `tiny` is ours; `real` is HuggingFaceTB/SmolVLM2-500M-Video-Instruct
# as used by lerobot/smolvla_base (vision: SigLIP-B/16 at 512 px; text: SmolLM2 960 wide).
TINY_VLM = {
    "vision": dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                   image_size=64, patch_size=16),
    "text": dict(hidden_size=64, intermediate_size=128, num_hidden_layers=4, num_attention_heads=4,
                 num_key_value_heads=2, head_dim=16, max_position_embeddings=512),
    "scale_factor": 2,
}
REAL_VLM = {
    "vision": dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12,
                   num_attention_heads=12, image_size=512, patch_size=16),
    "text": dict(hidden_size=960, intermediate_size=2560, num_hidden_layers=32,
                 num_attention_heads=15, num_key_value_heads=5, head_dim=64,
                 max_position_embeddings=8192, rope_theta=100000.0),
    "scale_factor": 4,
    "vocab_size": 49280,  # the real vocabulary size; the tokenizer written here is the small one
}


def tokens_per_camera(spec: dict) -> tuple[int, int]:
    """(rows, cols) of image tokens after the connector's pixel shuffle, for a VLM spec."""
    side = spec["vision"]["image_size"] // spec["vision"]["patch_size"] // spec["scale_factor"]
    return (side, side)


def tiny_vlm_folder() -> Path:
    """The tiny SmolVLM folder (created once, deterministic contents) for `vlm_model_name`."""
    return _vlm_folder("tiny_smolvlm", TINY_VLM)


def real_shape_vlm_folder() -> Path:
    """A folder with SmolVLM2-500M's architecture config (no weights) and the small tokenizer."""
    return _vlm_folder("real_shape_smolvlm", REAL_VLM)


def libero_smolvla_config(camera_keys, image_shape, state_dim, action_dim, **overrides):
    """A SmolVLAConfig whose features are the dataset's own (LIBERO names), other fields given."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    inputs = {key: PolicyFeature(FeatureType.VISUAL, tuple(image_shape)) for key in camera_keys}
    inputs[STATE_KEY] = PolicyFeature(FeatureType.STATE, (state_dim,))
    outputs = {ACTION_KEY: PolicyFeature(FeatureType.ACTION, (action_dim,))}
    # num_vlm_layers=0 keeps every text layer of the VLM (SmolVLA's default keeps 16 of 32).
    overrides.setdefault("num_vlm_layers", 0)
    return SmolVLAConfig(input_features=inputs, output_features=outputs, **overrides)


def sized_vlm(arch: Mapping[str, Any] | None = None) -> tuple[dict, dict]:
    """(the tiny SmolVLM spec, SmolVLAConfig overrides) of one size of the tiny ladder
    (backbones.tiny_sizes). `arch` holds what differs from the base tiny build: "text.<field>"
    and "vision.<field>" replace TINY_VLM's numbers, any other key is a SmolVLAConfig field
    (expert_width_multiplier). None or {}: the base build, exactly."""
    spec = {k: (dict(v) if isinstance(v, dict) else v) for k, v in TINY_VLM.items()}
    config: dict = {}
    for key, value in (arch or {}).items():
        part, _, name = key.partition(".")
        if name and part in ("text", "vision"):
            if name not in spec[part]:
                raise ValueError(f"tiny SmolVLA arch {key!r}: TINY_VLM[{part!r}] has no field "
                                 f"{name!r}; it has {sorted(spec[part])}")
            spec[part][name] = value
        else:
            config[key] = value
    return spec, config


def tiny_config(camera_keys=IMAGE_KEYS, image_hw=(64, 64), state_dim=LIBERO_STATE_DIM,
                action_dim=LIBERO_ACTION_DIM, chunk_size=10, device="cpu",
                arch: Mapping[str, Any] | None = None):
    """The tiny SmolVLA: images padded to the tiny tower's 64 px, chunk `chunk_size`; `arch`:
    a size of the ladder (sized_vlm), None the base size."""
    spec, overrides = sized_vlm(arch)
    side = spec["vision"]["image_size"]
    return libero_smolvla_config(
        camera_keys, (3, *image_hw), state_dim, action_dim,
        vlm_model_name=str(_vlm_folder("tiny_smolvlm", spec)), resize_imgs_with_padding=(side, side),
        chunk_size=chunk_size, n_action_steps=chunk_size, device=device, **overrides,
    )


def real_shape_forward():
    """smolvla_base's architecture without weights: (policy on meta, tower out, connector out).

    The policy (SmolVLAConfig defaults: 512 px, 16 of 32 text layers, chunk 50) is built on the
    meta device. The tower's position ids cannot run on meta tensors, so a CPU copy of the tower
    cut to one layer (layers keep shapes) and the real connector take one 512 px image.
    """
    import copy

    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from transformers.models.smolvlm.modeling_smolvlm import (
        SmolVLMConnector,
        SmolVLMVisionTransformer,
    )

    config = libero_smolvla_config(IMAGE_KEYS, (3, 256, 256), LIBERO_STATE_DIM, LIBERO_ACTION_DIM,
                                   vlm_model_name=str(real_shape_vlm_folder()), device="cpu",
                                   num_vlm_layers=16)
    with torch.device("meta"):
        policy = SmolVLAPolicy(config)
    vlm_config = policy.model.vlm_with_expert.get_vlm_model().config
    one_layer = copy.deepcopy(vlm_config.vision_config)
    one_layer.num_hidden_layers = 1
    side = config.resize_imgs_with_padding[0]
    with torch.random.fork_rng(devices=[]), torch.no_grad():
        tower = SmolVLMVisionTransformer(one_layer)
        tower_out = tower(pixel_values=torch.zeros(1, 3, side, side)).last_hidden_state
        tokens = SmolVLMConnector(vlm_config)(tower_out)
    return policy, tower_out, tokens


def _vocabulary() -> dict[str, int]:
    tokens = list(SPECIAL_TOKENS.values()) + sorted(set(TASK_WORDS)) + PUNCTUATION
    return {token: index for index, token in enumerate(tokens)}


def _vlm_folder(kind: str, spec: dict) -> Path:
    vocab = _vocabulary()
    blob = json.dumps({"format": FOLDER_FORMAT, "spec": spec, "vocab": vocab}, sort_keys=True)
    folder = cache_dir() / kind / hashlib.sha256(blob.encode()).hexdigest()[:12]
    if (folder / "config.json").is_file():
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    # Write next to the target and rename: parallel workers never see a half-written folder.
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=folder.parent))
    try:
        _write_vlm_files(staging, spec, vocab)
        try:
            os.rename(staging, folder)
        except OSError:  # another process won the race; its folder is identical
            if not (folder / "config.json").is_file():
                raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return folder


def _write_vlm_files(folder: Path, spec: dict, vocab: dict[str, int]) -> None:
    from tokenizers import Tokenizer, models, normalizers, pre_tokenizers
    from transformers import (
        PreTrainedTokenizerFast,
        SmolVLMConfig,
        SmolVLMImageProcessor,
        SmolVLMProcessor,
        SmolVLMVideoProcessor,
    )

    word_level = Tokenizer(models.WordLevel(vocab=vocab, unk_token=SPECIAL_TOKENS["unk"]))
    word_level.normalizer = normalizers.Lowercase()
    word_level.pre_tokenizer = pre_tokenizers.Whitespace()  # splits punctuation off words
    named = {k: v for k, v in SPECIAL_TOKENS.items() if k not in ("pad", "unk")}
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=word_level,
        unk_token=SPECIAL_TOKENS["unk"],
        pad_token=SPECIAL_TOKENS["pad"],
        extra_special_tokens=named,
    )
    side = spec["vision"]["image_size"]
    size = {"longest_edge": side}
    processor = SmolVLMProcessor(
        image_processor=SmolVLMImageProcessor(
            size=size, max_image_size=size, do_image_splitting=False
        ),
        tokenizer=tokenizer,
        video_processor=SmolVLMVideoProcessor(size=size, max_image_size=size),
        image_seq_len=tokens_per_camera(spec)[0] * tokens_per_camera(spec)[1],
    )
    processor.save_pretrained(folder)
    pad_id = vocab[SPECIAL_TOKENS["pad"]]
    config = SmolVLMConfig(
        vision_config=dict(spec["vision"]),
        text_config=dict(spec["text"], model_type="llama", pad_token_id=pad_id,
                         vocab_size=spec.get("vocab_size", len(vocab))),
        scale_factor=spec["scale_factor"],
        image_token_id=vocab[SPECIAL_TOKENS["image_token"]],
        pad_token_id=pad_id,
    )
    config.save_pretrained(folder)
    missing = {"config.json", "processor_config.json", "tokenizer.json", "tokenizer_config.json"}
    missing -= set(os.listdir(folder))
    if missing:
        raise RuntimeError(f"SmolVLM folder {folder} lacks {sorted(missing)} after writing it")
