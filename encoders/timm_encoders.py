"""timm encoders: the paper's four entries, "timm:<model>" names, and the frozen wrapper module.

Parameter counts below are of the REAL architectures, built with pretrained=False and
num_classes=0 (timm 1.0.31), and are checked by tests/test_encoders.py.
"""

from __future__ import annotations

import difflib
import math

import timm
import torch
import torch.nn.functional as F
from torch import Tensor

from encoders.base import Encoder, EncoderSpec, UnknownEncoder
from encoders.registry import EncoderUnavailable, register, register_prefix

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
TINY_SEED = 0

# Weight files timm looks for in a timm/* Hugging Face repo.
_HUB_WEIGHT_FILES = ("model.safetensors", "pytorch_model.bin", "open_clip_pytorch_model.bin")


class TimmEncoder(Encoder):
    """A frozen timm model. forward: (B, 3, H, W) float in [0,1] -> (B, C, h, w) float32."""

    def __init__(self, spec: EncoderSpec, model: torch.nn.Module, input_size: int, weights_id: str):
        super().__init__()
        self.spec = spec
        self.model = model
        self.input_size = input_size
        self.weights_id = weights_id
        self.channels = int(model.num_features)
        self.output_fmt = str(getattr(model, "output_fmt", "NCHW"))
        self.register_buffer("mean", torch.tensor(spec.mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(spec.std).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> "TimmEncoder":
        # Frozen means frozen: a parent's .train() must not switch BatchNorm/dropout back on.
        return super().train(False)

    @torch.no_grad()
    def forward(self, images: Tensor) -> Tensor:
        x = images.to(self.mean.dtype)
        if tuple(x.shape[-2:]) != (self.input_size, self.input_size):
            x = F.interpolate(x, size=(self.input_size, self.input_size), mode="bilinear",
                              antialias=True, align_corners=False)
        x = (x - self.mean) / self.std
        feats = self.model.forward_features(x)
        if self.spec.layout == "tokens":
            return _tokens_to_grid(feats, self.spec.num_prefix_tokens).float()
        if self.output_fmt == "NHWC":
            feats = feats.permute(0, 3, 1, 2)
        return feats.float().contiguous()


def _tokens_to_grid(tokens: Tensor, num_prefix_tokens: int) -> Tensor:
    """(B, P + h*w, C) tokens -> (B, C, h, w), dropping the P prefix (cls/register) tokens."""
    patches = tokens[:, num_prefix_tokens:]
    b, n, c = patches.shape
    side = math.isqrt(n)
    if side * side != n:
        raise ValueError(f"{n} patch tokens (after dropping {num_prefix_tokens} prefix tokens) do "
                         f"not form a square grid; check num_prefix_tokens of the encoder spec")
    return patches.transpose(1, 2).reshape(b, c, side, side)


def _fix(repo_id: str) -> str:
    return (f"fetch it on a machine with network (`huggingface-cli download {repo_id}`) into the "
            f"HF cache, or use source='tiny'")


def _missing_hub_repo(timm_name: str) -> str | None:
    """The HF repo id when it is known and none of its weight files is cached; else None."""
    from huggingface_hub import try_to_load_from_cache

    cfg = timm.models.get_pretrained_cfg(timm_name)
    repo_id = getattr(cfg, "hf_hub_id", None) if cfg is not None else None
    if not repo_id:
        return None
    files = (getattr(cfg, "hf_hub_filename", None),) + _HUB_WEIGHT_FILES
    cached = any(isinstance(try_to_load_from_cache(repo_id, f), str) for f in files if f)
    return None if cached else repo_id


def build_timm_encoder(spec: EncoderSpec, source: str) -> TimmEncoder:
    """Build a registered or on-the-fly timm spec; see encoders.registry.build_encoder."""
    assert spec.timm_name is not None, spec
    kwargs: dict = {"num_classes": 0}
    if source == "tiny":
        kwargs.update(spec.tiny_kwargs)
        input_size = spec.tiny_input_size or spec.input_size
    else:
        input_size = spec.input_size
    native = timm.models.get_pretrained_cfg(spec.timm_name)
    native_size = native.input_size[-1] if native is not None else input_size
    if spec.layout == "tokens" and "img_size" not in kwargs and input_size != native_size:
        kwargs["img_size"] = input_size  # ViT pos-embed built (and resampled on load) for our size

    if source == "tiny":
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(TINY_SEED)
            model = timm.create_model(spec.timm_name, pretrained=False, **kwargs)
        return TimmEncoder(spec, model, input_size, weights_id=f"tiny-init{TINY_SEED}")

    missing = _missing_hub_repo(spec.timm_name)
    if missing is not None:
        raise EncoderUnavailable(f"encoder {spec.name!r}: pretrained weights {missing!r} are not in "
                                 f"the local Hugging Face cache; {_fix(missing)}")
    try:
        model = timm.create_model(spec.timm_name, pretrained=True, **kwargs)
    except OSError as err:  # offline download attempt (URL-hosted weights, partial cache)
        raise EncoderUnavailable(f"encoder {spec.name!r}: could not load pretrained weights of "
                                 f"{spec.timm_name!r} ({type(err).__name__}: {err}); "
                                 f"{_fix('timm/' + spec.timm_name)}".replace("\n", " ")) from err
    cfg = model.pretrained_cfg
    weights_id = f"pretrained:{cfg.get('architecture', spec.timm_name)}.{cfg.get('tag') or ''}"
    return TimmEncoder(spec, model, input_size, weights_id=weights_id)


def resolve_timm(model_name: str) -> EncoderSpec:
    """Spec for "timm:<model_name>": layout, prefix tokens, input size and mean/std from timm."""
    if not timm.is_model(model_name):
        close = difflib.get_close_matches(model_name, timm.list_models(), n=3, cutoff=0.6)
        hint = f" Did you mean {' or '.join(repr('timm:' + c) for c in close)}?" if close else ""
        raise UnknownEncoder(f"unknown timm model {model_name!r}.{hint} "
                             f"See timm.list_models() for valid names.")
    with torch.device("meta"):  # architecture only: no memory, no init cost
        model = timm.create_model(model_name, pretrained=False, num_classes=0)
    cfg = model.pretrained_cfg
    tokens = hasattr(model, "num_prefix_tokens")
    return EncoderSpec(
        name=f"timm:{model_name}",
        timm_name=model_name,
        input_size=int(cfg.get("input_size", (3, 224, 224))[-1]),
        mean=tuple(cfg.get("mean", IMAGENET_MEAN)),
        std=tuple(cfg.get("std", IMAGENET_STD)),
        num_prefix_tokens=int(getattr(model, "num_prefix_tokens", 0)) if tokens else 0,
        layout="tokens" if tokens else "map",
        description=f"timm model {model_name} taken as is ({model.num_features} channels)",
    )


register_prefix("timm", resolve_timm, build_timm_encoder)

# --- The paper's encoders. Tiny profiles: same architecture, ~0.1-0.3M params, 2x2..4x4 grids. ---

register(EncoderSpec(
    name="siglip", timm_name="vit_base_patch16_siglip_224.webli", input_size=224,
    mean=(0.5, 0.5, 0.5), std=(0.5, 0.5, 0.5), num_prefix_tokens=0, layout="tokens",
    tiny_kwargs=dict(depth=2, embed_dim=64, num_heads=2, img_size=64), tiny_input_size=64,
    description="SigLIP-B/16, SigLIP 1 webli weights (SmolVLA's tower family; no cls token): "
                "92.9M params, 768 ch, 14x14 grid at 224; tiny: 64 ch, 4x4 grid at 64 px"),
    build_timm_encoder)

register(EncoderSpec(
    name="dinov2_s", timm_name="vit_small_patch14_dinov2", input_size=224,
    mean=IMAGENET_MEAN, std=IMAGENET_STD, num_prefix_tokens=1, layout="tokens",
    # 56 = 4 patches of 14: the tiny input keeps the stride exact, as 224 = 16 x 14 does.
    tiny_kwargs=dict(depth=2, embed_dim=64, num_heads=2, img_size=56), tiny_input_size=56,
    description="DINOv2-S/14 (1 cls token): 22.1M params at native 518 px (21.6M with the "
                "pos-embed resampled to 224), 384 ch, 16x16 grid at 224; "
                "tiny: 64 ch, 4x4 grid at 56 px"), build_timm_encoder)

register(EncoderSpec(
    name="fastvit", timm_name="fastvit_sa12", input_size=256,
    mean=IMAGENET_MEAN, std=IMAGENET_STD, layout="map",
    # Stage widths must each divide the next (grouped downsampling convs).
    tiny_kwargs=dict(layers=(1, 1, 1, 1), embed_dims=(16, 32, 64, 128)), tiny_input_size=64,
    description="FastViT-SA12 (timm's pretrained size 256): 10.6M params, 1024 ch (final conv = "
                "2 x 512), 8x8 grid at 256; tiny: 256 ch, 2x2 grid at 64 px"), build_timm_encoder)

register(EncoderSpec(
    name="repvit", timm_name="repvit_m1", input_size=224,
    mean=IMAGENET_MEAN, std=IMAGENET_STD, layout="map",
    tiny_kwargs=dict(embed_dim=(16, 32, 48, 64), depth=(1, 1, 1, 1)), tiny_input_size=64,
    description="RepViT-M1: 4.7M params, 384 ch, 7x7 grid at 224; "
                "tiny: 64 ch, 2x2 grid at 64 px"), build_timm_encoder)
