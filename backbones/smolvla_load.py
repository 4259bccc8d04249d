"""Loading a saved SmolVLA (a local folder, or a hub release in the HF cache) fitted to the
suite's features; what that load reads from the hub (for the preflight); one-line errors."""

from __future__ import annotations

from pathlib import Path

import torch
from lerobot_policy_graft.configuration_graft import config_from_pretrained

from backbones import hub
from backbones.base import only_step
from ondisk.hubcache import hub_artifact
from ondisk.libero_format import (
    ACTION_KEY, IMAGE_KEYS, LIBERO_ACTION_DIM, LIBERO_STATE_DIM, STATE_KEY,
)

VLM_REPO_ID = "HuggingFaceTB/SmolVLM2-500M-Video-Instruct"  # smolvla_base's vlm_model_name
# save_pretrained copies a local SmolVLM folder (the tiny one) here so the folder is self-contained.
VENDORED_VLM_DIR = "smolvlm"


def load_parts(
    path_or_repo_id: str,
    stats: dict | None = None,
    *,
    rename_map: dict[str, str] | None = None,
    camera_keys=IMAGE_KEYS,
    state_dim: int = LIBERO_STATE_DIM,
    action_dim: int = LIBERO_ACTION_DIM,
    device: str | None = None,
    revision: str | None = None,
) -> tuple:
    """(policy, preprocessor, postprocessor) of a saved SmolVLA (local folder or hub id in the HF
    cache), fitted to LIBERO's features; backbones.smolvla.load_policy wraps them.

    When the checkpoint's features differ from LIBERO's (smolvla_base: cameras camera1/2/3, 6-dim
    state and action), its cameras are renamed (`rename_map`, default by hub.CAMERA_LAYOUTS),
    unused ones dropped, state/action resized (both are zero-padded to 32 inside anyway), and
    `stats` (dataset stats) are required: its saved normaliser does not cover LIBERO. With
    `stats`, the processors are rebuilt from them; without, the saved processors are loaded with
    our device and features, and their own stats must cover state and action.
    """
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    local = Path(path_or_repo_id).expanduser()
    source = str(local) if local.is_dir() else path_or_repo_id
    if not local.is_dir():
        if path_or_repo_id.startswith(("/", ".", "~")) or path_or_repo_id.count("/") > 1:
            raise FileNotFoundError(f"no SmolVLA checkpoint folder at {path_or_repo_id}")
        hub.require_present(artifacts(path_or_repo_id, revision, f"backbone {path_or_repo_id}")[:1])
        device = device or hub.default_device()
    with _hub_errors_as_unavailable(path_or_repo_id, revision=revision):
        config = config_from_pretrained(source, revision)
    if config.type != "smolvla":
        raise ValueError(f"{path_or_repo_id} holds a {config.type!r} policy, not 'smolvla'")
    config.load_vlm_weights = False  # the checkpoint carries every VLM weight; keep float32
    if device is not None:
        config.device = device
    _point_at_vlm(config, local, path_or_repo_id)
    if rename_map is None:
        rename_map = hub.libero_rename_map(list(config.image_features), "smolvla")
        rename_map = {src: dst for src, dst in rename_map.items() if src != dst}
    adapted = _fit_features(config, rename_map, camera_keys, state_dim, action_dim)
    if adapted and stats is None and not _saved_stats_fit(source, revision, state_dim, action_dim):
        raise ValueError(
            f"{path_or_repo_id}'s saved normaliser covers its own features, not LIBERO's "
            f"(state {state_dim}, action {action_dim}): pass stats=<dataset stats> to load_policy"
        )
    with _hub_errors_as_unavailable(path_or_repo_id, config.vlm_model_name, revision):
        policy = SmolVLAPolicy.from_pretrained(source, config=config, revision=revision)
    _check_all_weights_loaded(policy, source, revision)
    policy.to(config.device)

    preprocessor, postprocessor = _processors(config, source, path_or_repo_id, revision, stats,
                                              rename_map)
    hub.check_normalizer_covers(preprocessor, source)
    hub.check_normalizer_covers(postprocessor, source)
    return policy, preprocessor, postprocessor


def _point_at_vlm(config, local: Path, needed_by: str) -> None:
    """The VLM config/tokenizer: vendored in a saved folder, else a local folder or the cache."""
    vendored = local / VENDORED_VLM_DIR
    if vendored.is_dir():
        config.vlm_model_name = str(vendored)
    elif not Path(config.vlm_model_name).is_dir():
        hub.require_present([_vlm_artifact(config.vlm_model_name, f"backbone {needed_by}")])


def _saved_stats_fit(source: str, revision: str | None, state_dim: int, action_dim: int) -> bool:
    """Do the checkpoint's saved normaliser stats have LIBERO's state and action widths?"""
    stats = hub.saved_normalizer_stats(source, revision) or {}
    widths = {key: tuple(stats.get(key, {}).get("mean", torch.empty(0)).shape)
              for key in (STATE_KEY, ACTION_KEY)}
    return widths == {STATE_KEY: (state_dim,), ACTION_KEY: (action_dim,)}


VLM_INCLUDE = ("*.json", "*.txt", "*.jinja")  # config, processor, tokenizer: not the 1.9 GB weights


def _vlm_artifact(vlm_repo_id: str, needed_by: str):
    return hub_artifact(
        "vlm config", vlm_repo_id, ("config.json", "tokenizer_config.json", "processor_config.json"),
        needed_by, include=VLM_INCLUDE,
        note="LeRobot reads its config, processor and tokenizer at main (no revision); "
             "the checkpoint carries the VLM weights",
    )


def artifacts(repo_id: str, revision: str | None, needed_by: str, vlm_repo_id: str = VLM_REPO_ID) -> list:
    """What loading `repo_id` reads from the hub: the checkpoint, and its VLM's config/tokenizer."""
    return [hub_artifact("policy", repo_id, ("config.json", "model.safetensors"), needed_by, revision),
            _vlm_artifact(vlm_repo_id, needed_by)]


def _fit_features(config, rename_map, camera_keys, state_dim, action_dim) -> bool:
    """Point the config at LIBERO's cameras/state/action in place; True if anything changed."""
    from lerobot.configs import FeatureType, PolicyFeature

    wanted = [rename_map.get(k, k) for k in camera_keys]
    unknown = [k for k in wanted if k not in config.image_features]
    if unknown:
        raise ValueError(
            f"cameras {list(camera_keys)} map to {unknown} under rename map {rename_map}, but the "
            f"checkpoint's cameras are {list(config.image_features)}: pass rename_map=..."
        )
    inputs = {
        key: feature for key, feature in config.input_features.items()
        if feature.type != FeatureType.VISUAL or key in wanted  # checkpoint order is kept
    }
    inputs[STATE_KEY] = PolicyFeature(FeatureType.STATE, (state_dim,))
    outputs = {ACTION_KEY: PolicyFeature(FeatureType.ACTION, (action_dim,))}
    changed = inputs != config.input_features or outputs != config.output_features
    config.input_features, config.output_features = inputs, outputs
    return changed


def _check_all_weights_loaded(policy, source: str, revision: str | None = None) -> None:
    """LeRobot loads with strict=False and only logs missing keys: make a miss an error."""
    from huggingface_hub import hf_hub_download
    from safetensors import safe_open

    local = Path(source) / "model.safetensors"
    model_file = local if local.is_file() else hf_hub_download(source, "model.safetensors",
                                                               revision=revision)
    with safe_open(str(model_file), framework="pt") as handle:
        saved = set(handle.keys())
    state = policy.state_dict()
    saved_ptrs = {state[k].data_ptr() for k in saved if k in state}  # tied weights are saved once
    missing = sorted(k for k in state if k not in saved and state[k].data_ptr() not in saved_ptrs)
    if missing:
        raise RuntimeError(f"{source} lacks {len(missing)} policy weights, e.g. {missing[:3]}")


def _hub_errors_as_unavailable(repo_id: str, vlm_repo_id: str = VLM_REPO_ID,
                               revision: str | None = None):
    return hub.errors_as_unavailable(
        repo_id, lambda: artifacts(repo_id, revision, repo_id, vlm_repo_id), local=(vlm_repo_id,))


def _processors(config, source: str, path_or_repo_id: str, revision: str | None,
                stats: dict | None, rename_map: dict[str, str]):
    """With `stats` (dataset stats), pipelines rebuilt from them; else the saved pipelines with
    LeRobot's train-time overrides (our device, features, rename map; their own stats)."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.processor import RenameObservationsProcessorStep

    if stats is not None:
        preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
        if rename_map:
            only_step(preprocessor, RenameObservationsProcessorStep).rename_map = dict(rename_map)
        return preprocessor, postprocessor
    pre_over, post_over = hub.saved_processor_overrides(config, config.device, None, rename_map)
    pre_over["tokenizer_processor"] = {"tokenizer_name": config.vlm_model_name}
    with _hub_errors_as_unavailable(path_or_repo_id, revision=revision):
        return make_pre_post_processors(
            config, pretrained_path=source, pretrained_revision=revision,
            preprocessor_overrides=pre_over, postprocessor_overrides=post_over,
        )
