"""pi0.5 (LeRobot 0.6.1 `PI05Policy`) behind the `Backbone` interface, real or tiny.

Graft point: `PaliGemmaWithExpertModel.embed_image` (modeling_pi05.py:284-293), which returns
SigLIP -> multi_modal_projector features; no scaling is applied to image embeddings afterwards
(:492-502). The loss calls the INNER `PI05Pytorch.forward` (:564-611), because `PI05Policy.forward`
(:1058-1096) takes no noise/time and counts padded chunk steps.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
from pathlib import Path
from typing import Iterator

import torch
from torch import Tensor

from backbones.base import Backbone, BackboneInfo, BackboneUnavailable, ImageEmbedder
from backbones.tiny_pi05 import (
    LEROBOT_PIN,
    TOKENIZER_DIRNAME,
    TinyPI05Arch,
    ensure_tiny_tokenizer,
    require_pinned_lerobot,
    tiny_pi05_patches,
    tiny_vocabulary,
)
from backbones import hub
from bench.paths import cache_dir

REAL_REPO_ID = "lerobot/pi05_base"
PALIGEMMA_TOKENIZER_REPO = "google/paligemma-3b-pt-224"  # processor_pi05.py:141
MARKER_FILE = "graftbench_pi05.json"  # written by save_pretrained: tiny arch, cameras, rename map
TOKENIZER_SUBDIR = "tokenizer"  # the tiny tokenizer travels inside a saved tiny checkpoint
ACTION_KEY, STATE_KEY = "action", "observation.state"
PAD_KEY = "action_is_pad"
TOKENS_KEY = "observation.language.tokens"  # lerobot.utils.constants.OBS_LANGUAGE_TOKENS
TOKEN_MASK_KEY = "observation.language.attention_mask"

NATIVE_FEATURE_DOC = (
    "SigLIP vision tower last_hidden_state (after its post-layernorm, BEFORE PaliGemma's "
    "multi_modal_projector), computed from the image the policy feeds embed_image (resized with "
    "padding to config.image_resolution, scaled to [-1, 1]); tokens reshaped row-major to "
    "(B, C, h, w): (B, 1152, 16, 16) for pi05_base, (B, 32, 4, 4) for the tiny build"
)

INFO_REAL = BackboneInfo(
    name="pi05",
    native_grid=(16, 16),  # 224 px / patch 14 (configuration_pi05.py:25; SigLIP So400m)
    lm_width=2048,  # gemma_2b width (modeling_pi05.py:169-177)
    chunk_size=50,
    max_action_dim=32,
    num_denoise_steps=10,
    native_feature_doc=NATIVE_FEATURE_DOC,
)

# Cameras: lerobot/pi05_base names its cameras base_0_rgb / left_wrist_0_rgb / right_wrist_0_rgb
# (docs/HUB_FACTS.md); LIBERO's agent view feeds base_0_rgb and its wrist left_wrist_0_rgb
# (backbones.hub.CAMERA_LAYOUTS). The unmapped right_wrist slot would be fed as a -1 image with
# mask False (modeling_pi05.py:1009-1014). We drop unmapped cameras from the config instead:
# masked tokens neither attend nor shift position ids (cumsum of pad masks, :584), so outputs are
# unchanged (bit-identical on the tiny build, see tests), and every embed_image call is one suite
# camera.


class PI05Backbone(Backbone):
    """A real `PI05Policy` with its own pre/post processors (see backbones.base for the contract)."""

    def __init__(
        self,
        policy,  # lerobot PI05Policy
        preprocessor,  # lerobot PolicyProcessorPipeline (raw batch -> prepared batch)
        postprocessor,  # lerobot PolicyProcessorPipeline (normalised actions -> raw)
        camera_keys: tuple[str, ...],
        tiny_arch: TinyPI05Arch | None = None,
        rename_map: dict[str, str] | None = None,
    ) -> None:
        self.policy = policy
        self.preprocessor = preprocessor
        self.postprocessor = postprocessor
        self.camera_keys = tuple(camera_keys)
        self.tiny_arch: TinyPI05Arch | None = tiny_arch
        self.rename_map: dict[str, str] = dict(rename_map or {})
        self.info = _info_from_policy(policy)
        self.action_dim = policy.config.output_features[ACTION_KEY].shape[0]

    # -- processing -------------------------------------------------------------------------
    def preprocess(self, raw: dict) -> dict:
        return self.preprocessor(dict(raw))

    def normalize_actions(self, actions: Tensor) -> Tensor:
        return _on_action(_only_step(self.preprocessor, "NormalizerProcessorStep"), actions)

    def unnormalize_actions(self, actions: Tensor) -> Tensor:
        # The step alone, not the whole post-processor: that one also moves actions to the CPU.
        return _on_action(_only_step(self.postprocessor, "UnnormalizerProcessorStep"), actions)

    # -- graft point ------------------------------------------------------------------------
    @contextlib.contextmanager
    def image_embedder(self, fn: ImageEmbedder) -> Iterator[None]:
        # object.__setattr__: nn.Module.__setattr__ would register an nn.Module `fn` as a
        # submodule of the frozen policy (its parameters and state dict).
        owner = self.policy.model.paligemma_with_expert
        previous = owner.__dict__.get("embed_image")
        object.__setattr__(owner, "embed_image", fn)
        try:
            yield
        finally:
            if previous is None:
                del owner.__dict__["embed_image"]
            else:
                object.__setattr__(owner, "embed_image", previous)

    def native_tower_grid(self, image: Tensor) -> Tensor:
        tower = self.policy.model.paligemma_with_expert.paligemma.model.vision_tower
        tokens = tower(image.to(torch.float32)).last_hidden_state  # (B, h*w, C)
        batch, count, channels = tokens.shape
        side = math.isqrt(count)
        if side * side != count:
            raise RuntimeError(f"SigLIP gave {count} tokens, not a square grid")
        return tokens.transpose(1, 2).reshape(batch, channels, side, side)

    # -- loss and sampling ------------------------------------------------------------------
    def loss(self, batch: dict, noise: Tensor, time: Tensor) -> Tensor:
        """(B,) flow-matching loss: mean over real action dims, then over real (unpadded) steps.

        The action expert attends across the whole chunk, so the values held at padded steps
        would still reach real steps through x_t. They are set to the last real action first
        (what LeRobotDataset delivers past an episode end, so a no-op on its batches), making
        the loss a function of real steps only.
        """
        policy = self.policy
        images, img_masks = policy._preprocess_images(batch)  # the policy's own pixel prep
        tokens, masks = batch[TOKENS_KEY], batch[TOKEN_MASK_KEY]
        is_pad = batch[PAD_KEY].to(batch[ACTION_KEY].device).bool()
        held = _hold_last_real_action(batch[ACTION_KEY], is_pad)
        actions = policy.prepare_action({ACTION_KEY: held})  # zero-pad to max_action_dim
        device = actions.device
        per_element = policy.model.forward(
            images, img_masks, tokens, masks, actions, noise.to(device), time.to(device)
        )  # (B, chunk, max_action_dim)
        per_step = per_element[:, :, : self.action_dim].mean(dim=2)
        real_steps = (~is_pad).to(per_step.dtype)
        return (per_step * real_steps).sum(dim=1) / real_steps.sum(dim=1).clamp(min=1.0)

    def sample_time(self, batch_size: int, generator: torch.Generator) -> Tensor:
        # Beta(alpha, beta) * scale + offset (PI05Pytorch.sample_time, modeling_pi05.py:473-481),
        # drawn as X / (X + Y) with X, Y ~ Gamma because torch's Beta takes no generator.
        cfg = self.policy.config
        alpha = torch.full((batch_size,), float(cfg.time_sampling_beta_alpha))
        beta = torch.full((batch_size,), float(cfg.time_sampling_beta_beta))
        x = torch._standard_gamma(alpha, generator=generator)
        y = torch._standard_gamma(beta, generator=generator)
        return (x / (x + y)) * cfg.time_sampling_scale + cfg.time_sampling_offset

    @torch.no_grad()
    def sample_actions(self, batch: dict, noise: Tensor) -> Tensor:
        # predict_action_chunk (modeling_pi05.py:1040-1056): normalised actions (no
        # post-processor), already cut to the real action dims; 10 Euler steps by default.
        device = batch[TOKENS_KEY].device
        return self.policy.predict_action_chunk(batch, noise=noise.to(device, torch.float32))

    def language_model(self) -> torch.nn.Module:
        return self.policy.model.paligemma_with_expert.paligemma.model.language_model


def _only_step(pipeline, class_name: str):
    """The single step of `pipeline` whose class is named `class_name`."""
    steps = [s for s in pipeline.steps if type(s).__name__ == class_name]
    if len(steps) != 1:
        names = [type(s).__name__ for s in pipeline.steps]
        raise RuntimeError(f"expected one {class_name} among the processor steps {names}")
    return steps[0]


def _on_action(step, actions: Tensor) -> Tensor:
    """Apply one (un)normaliser step to an action tensor alone (its device is kept)."""
    from lerobot.processor import TransitionKey, create_transition

    return step(create_transition(action=actions))[TransitionKey.ACTION]


def _hold_last_real_action(actions: Tensor, is_pad: Tensor) -> Tensor:
    """(B, T, A) actions with every padded step replaced by the latest real step before it."""
    steps = torch.arange(actions.shape[1], device=actions.device).expand_as(is_pad)
    latest_real = torch.cummax(torch.where(is_pad, 0, steps), dim=1).values  # (B, T)
    return torch.gather(actions, 1, latest_real[..., None].expand_as(actions))


def _info_from_policy(policy) -> BackboneInfo:
    paligemma = policy.model.paligemma_with_expert.paligemma
    vision = paligemma.config.vision_config
    side = vision.image_size // vision.patch_size
    return BackboneInfo(
        name="pi05",
        native_grid=(side, side),
        lm_width=paligemma.config.text_config.hidden_size,
        chunk_size=policy.config.chunk_size,
        max_action_dim=policy.config.max_action_dim,
        num_denoise_steps=policy.config.num_inference_steps,
        native_feature_doc=NATIVE_FEATURE_DOC,
    )


# -- building -------------------------------------------------------------------------------
def build_tiny_policy(
    stats: dict,
    camera_keys=("observation.images.image", "observation.images.wrist_image"),
    image_hw: tuple[int, int] = (64, 64),
    state_dim: int = 8,
    action_dim: int = 7,
    chunk_size: int = 10,
    seed: int = 0,
) -> PI05Backbone:
    """A real PI05Policy with tiny sizes (~0.2M parameters), offline, deterministic from `seed`."""
    require_pinned_lerobot()
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.pi05.configuration_pi05 import PI05Config
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    _check_stats(stats, state_dim, action_dim)
    arch = TinyPI05Arch(vocab_size=_round_up(len(tiny_vocabulary()), 64))
    if image_hw[0] != image_hw[1] or image_hw[0] % arch.patch_size:
        raise ValueError(f"image_hw {image_hw} must be square and a multiple of patch {arch.patch_size}")
    tokenizer_dir = ensure_tiny_tokenizer(cache_dir() / TOKENIZER_DIRNAME)
    inputs = {key: PolicyFeature(FeatureType.VISUAL, (3, *image_hw)) for key in camera_keys}
    inputs[STATE_KEY] = PolicyFeature(FeatureType.STATE, (state_dim,))
    config = PI05Config(
        input_features=inputs,
        output_features={ACTION_KEY: PolicyFeature(FeatureType.ACTION, (action_dim,))},
        chunk_size=chunk_size,
        n_action_steps=chunk_size,
        image_resolution=tuple(image_hw),
        tokenizer_max_length=48,  # the tiny prompts fit in ~40 tokens; 200 only costs time
        device="cpu",
    )
    with torch.random.fork_rng(devices=[]), tiny_pi05_patches(arch, tokenizer_dir):
        torch.manual_seed(seed)
        policy = PI05Policy(config)
        preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
    return PI05Backbone(policy, preprocessor, postprocessor, camera_keys, tiny_arch=arch)


def save_pretrained(backbone: PI05Backbone, folder: str | os.PathLike) -> Path:
    """Policy (config + safetensors), both processors and our marker into `folder`."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    backbone.policy.save_pretrained(folder)
    backbone.preprocessor.save_pretrained(folder)
    backbone.postprocessor.save_pretrained(folder)
    marker = {
        "lerobot": LEROBOT_PIN,
        "camera_keys": list(backbone.camera_keys),
        "rename_map": backbone.rename_map,
        "tiny_arch": backbone.tiny_arch.to_dict() if backbone.tiny_arch else None,
    }
    if backbone.tiny_arch is not None:  # the tokenizer in use travels with the checkpoint
        tokenizer_step = _only_step(backbone.preprocessor, "TokenizerProcessorStep")
        tokenizer_step.input_tokenizer.save_pretrained(folder / TOKENIZER_SUBDIR)
    (folder / MARKER_FILE).write_text(json.dumps(marker, indent=2, sort_keys=True))
    return folder


def load_policy(path_or_repo_id: str, stats: dict | None = None, *, revision: str | None = None,
                device: str | None = None) -> PI05Backbone:
    """A saved folder (tiny or real) or a hub repo id from the HF cache, on `device` (default: the
    checkpoint's own for a folder, CUDA when available for a hub id). `stats` (dataset stats)
    replace the saved ones; without them the checkpoint's own saved stats are used, and must cover
    the state and action."""
    require_pinned_lerobot()
    folder = Path(path_or_repo_id).expanduser()
    if folder.is_dir():
        return _load(str(folder), stats, marker_dir=folder, revision=None, device=device)
    if path_or_repo_id.startswith(("/", ".", "~")) or path_or_repo_id.count("/") != 1:
        raise FileNotFoundError(
            f"no pi0.5 checkpoint folder at {path_or_repo_id!r} (and it is not an owner/name hub id)"
        )
    _require_cached(path_or_repo_id, revision)
    return _load(path_or_repo_id, stats, marker_dir=None, revision=revision,
                 device=device or hub.default_device())


def _read_marker(source: str, marker_dir: Path | None, revision: str | None) -> dict:
    """graftbench's marker: a saved folder's (tiny arch, cameras, rename map) or, for a hub repo,
    only its tiny arch (the offline hub-cache world; a real release has no marker)."""
    if marker_dir is not None:
        path = marker_dir / MARKER_FILE
        return json.loads(path.read_text()) if path.is_file() else {}
    path = hub.cached_file(source, MARKER_FILE, revision)
    return {"tiny_arch": json.loads(path.read_text()).get("tiny_arch")} if path else {}


def _load(source: str, stats: dict | None, marker_dir: Path | None, revision: str | None,
          device: str | None) -> PI05Backbone:
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors

    marker = _read_marker(source, marker_dir, revision)
    arch = TinyPI05Arch.from_dict(marker["tiny_arch"]) if marker.get("tiny_arch") else None
    with _hub_errors_as_unavailable(source, revision):
        config = PreTrainedConfig.from_pretrained(source, revision=revision)
    if device is not None:
        config.device = device
    if marker.get("camera_keys"):
        rename_map, camera_keys = marker["rename_map"], tuple(marker["camera_keys"])
    else:
        rename_map, camera_keys = _adapt_real_config(config, stats)
    # A saved tiny folder carries its tokenizer; a hub repo reads google/paligemma-3b-pt-224's.
    tokenizer_dir = marker_dir / TOKENIZER_SUBDIR if arch and marker_dir else None
    patches = tiny_pi05_patches(arch, tokenizer_dir) if arch else contextlib.nullcontext()
    with patches, _hub_errors_as_unavailable(source, revision):
        policy = _policy_from_pretrained(source, config, revision)
        policy.to(config.device)
        if marker_dir is not None or hub.cached_file(source, "policy_preprocessor.json", revision):
            pre_over, post_over = hub.saved_processor_overrides(
                policy.config, config.device, stats, rename_map)
            if tokenizer_dir is not None:
                pre_over["tokenizer_processor"] = {"tokenizer_name": str(tokenizer_dir)}
            pre, post = make_pre_post_processors(
                policy.config, pretrained_path=source, pretrained_revision=revision,
                preprocessor_overrides=pre_over, postprocessor_overrides=post_over,
            )
        else:  # a hub checkpoint saved before LeRobot's processor pipelines
            if stats is None:
                raise ValueError(f"{source} has no saved processors: pass dataset stats to load_policy")
            pre, post = make_pre_post_processors(policy.config, dataset_stats=stats)
            if rename_map:
                _only_step(pre, "RenameObservationsProcessorStep").rename_map = dict(rename_map)
    hub.check_normalizer_covers(pre, source)
    hub.check_normalizer_covers(post, source)
    return PI05Backbone(policy, pre, post, camera_keys, tiny_arch=arch, rename_map=rename_map)


def _adapt_real_config(config, stats: dict | None) -> tuple[dict[str, str], tuple[str, ...]]:
    """LIBERO view of a released config: rename map, cameras kept, state/action width (in place)."""
    from lerobot.configs import FeatureType, PolicyFeature

    image_keys = list(config.image_features)
    rename_map = hub.libero_rename_map(image_keys, config.type)
    policy_keys = list(rename_map.values())
    for key in image_keys:  # unmapped cameras are dropped, not masked (see CAMERA_LAYOUTS above)
        if key not in policy_keys:
            del config.input_features[key]
    rename_map = {src: dst for src, dst in rename_map.items() if src != dst}
    dims = {key: len(stats[key]["q01"]) if stats else default
            for key, default in ((STATE_KEY, 8), (ACTION_KEY, 7))}  # LIBERO's 8 / 7 real dims
    config.input_features[STATE_KEY] = PolicyFeature(FeatureType.STATE, (dims[STATE_KEY],))
    config.output_features[ACTION_KEY] = PolicyFeature(FeatureType.ACTION, (dims[ACTION_KEY],))
    return rename_map, hub.LIBERO_CAMERAS


def _policy_from_pretrained(source: str, config, revision: str | None = None):
    """PI05Policy.from_pretrained, failing loudly where lerobot would keep random weights."""
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    # modeling_pi05.py:810-813 and :859-860 print and return the randomly initialised model
    # when the weights cannot be read or do not match; we refuse that.
    captured = io.StringIO()
    with contextlib.redirect_stdout(captured):
        policy = PI05Policy.from_pretrained(source, config=config, revision=revision)
    if "Could not load" in captured.getvalue():
        raise RuntimeError(
            f"PI05Policy.from_pretrained({source!r}) kept random weights:\n{captured.getvalue()}"
        )
    return policy


# config.json too: transformers 5.5's AutoTokenizer reads the repo's model config first (found
# offline by the hub-cache world: without it the tokenizer does not load).
TOKENIZER_INCLUDE = ("config.json", "tokenizer*", "special_tokens_map.json", "added_tokens.json")
TOKENIZER_NOTE = (
    "gated: accept the licence at https://huggingface.co/google/paligemma-3b-pt-224 and run "
    "`hf auth login` first; the --include patterns fetch the ~22 MB tokenizer, not 11.7 GB of weights"
)


def artifacts(repo_id: str, revision: str | None, needed_by: str) -> list:
    """What loading `repo_id` reads from the hub: the checkpoint and the PaliGemma tokenizer
    (LeRobot reads the tokenizer at its main revision: processor_pi05.py ~141 takes no revision)."""
    return [
        hub.hub_artifact("policy", repo_id, ("config.json", "model.safetensors"), needed_by, revision),
        hub.hub_artifact("tokenizer", PALIGEMMA_TOKENIZER_REPO,
                         ("config.json", "tokenizer_config.json", "tokenizer.json"), needed_by,
                         include=TOKENIZER_INCLUDE, note=TOKENIZER_NOTE),
    ]


def _require_cached(repo_id: str, revision: str | None = None) -> None:
    """Fail fast, in one line, when offline and the checkpoint or its tokenizer is not cached."""
    hub.require_present(artifacts(repo_id, revision, f"backbone {repo_id}"))


@contextlib.contextmanager
def _hub_errors_as_unavailable(repo_id: str, revision: str | None) -> Iterator[None]:
    """Hub/auth errors while loading (online: gated tokenizer, missing revision) as one line."""
    from huggingface_hub.errors import HfHubHTTPError

    try:
        yield
    except (HfHubHTTPError, OSError) as error:  # transformers and LeRobot raise OSError subclasses
        if Path(repo_id).is_dir():
            raise
        fixes = "; ".join(f"`{a.fix}`" + (f" ({a.note})" if a.note else "")
                          for a in artifacts(repo_id, revision, repo_id))
        reason = " ".join(str(error).split())[:240]
        raise BackboneUnavailable(
            f"could not load {repo_id} or its tokenizer ({type(error).__name__}: {reason}); "
            f"fix: {fixes or 'check the network and your hub token'}"
        ) from error


def check_real_shapes() -> dict[str, int]:
    """Build the REAL pi0.5 model on the meta device (no weights) and embed one 224 px image.

    Returns {"tokens_per_camera": 256, "lm_width": 2048} for LeRobot's default PI05Config.
    """
    require_pinned_lerobot()
    from lerobot.policies.pi05.configuration_pi05 import PI05Config
    from lerobot.policies.pi05.modeling_pi05 import PI05Pytorch

    config = PI05Config(device="cpu")
    with torch.device("meta"):
        model = PI05Pytorch(config)
        image = torch.empty(1, 3, *config.image_resolution)
        embedded = model.paligemma_with_expert.embed_image(image)  # (1, N, lm_width), meta
    return {"tokens_per_camera": int(embedded.shape[1]), "lm_width": int(embedded.shape[2])}


def _check_stats(stats: dict, state_dim: int, action_dim: int) -> None:
    for key, dim in ((STATE_KEY, state_dim), (ACTION_KEY, action_dim)):
        for name in ("q01", "q99"):  # pi0.5 normalises state and action by quantiles
            values = stats.get(key, {}).get(name)
            if values is None or len(values) != dim:
                raise ValueError(
                    f"stats[{key!r}][{name!r}] must have {dim} values (pi0.5 uses QUANTILES "
                    f"normalisation), got {None if values is None else len(values)}"
                )


def _round_up(value: int, multiple: int) -> int:
    return -(-value // multiple) * multiple
