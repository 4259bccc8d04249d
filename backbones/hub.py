"""What both adapters need from the Hugging Face cache and LeRobot's saved processors.

One owner for: the offline switch, cache look-ups at a pinned revision, the overrides that make a
checkpoint's SAVED processor pipeline fit the policy we built (LeRobot's own lerobot_train.py
~356-377 passes the same ones), and the check that the resulting normaliser covers the state and
action it will see (a hub `policy_preprocessor.json` may carry `"features": {}`, which makes the
normaliser pass the state through untouched without a word).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import torch

STATE_KEY, ACTION_KEY = "observation.state", "action"


def hub_offline() -> bool:
    """HF_HUB_OFFLINE as set now (env) or as huggingface_hub read it at import."""
    from huggingface_hub import constants

    flag = os.environ.get("HF_HUB_OFFLINE", "").strip().upper() in {"1", "ON", "YES", "TRUE"}
    return flag or bool(constants.HF_HUB_OFFLINE)


def cached_file(repo_id: str, filename: str, revision: str | None = None) -> Path | None:
    """The cached path of `filename` in `repo_id` at `revision` (default main), or None."""
    from huggingface_hub import try_to_load_from_cache

    found = try_to_load_from_cache(repo_id, filename, revision=revision)
    return Path(found) if isinstance(found, str) else None


def resolved_revision(repo_id: str, revision: str | None = None, repo_type: str = "model") -> str | None:
    """The commit sha the cache holds for `repo_id` at `revision` (a sha stays itself)."""
    from huggingface_hub import constants

    if revision and len(revision) == 40 and all(c in "0123456789abcdef" for c in revision):
        return revision
    folder = Path(constants.HF_HUB_CACHE) / f"{repo_type}s--{repo_id.replace('/', '--')}"
    ref = folder / "refs" / (revision or "main")
    return ref.read_text().strip() if ref.is_file() else None


def default_device() -> str:
    """Where a hub policy runs: the current CUDA device when there is one, else the CPU."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def saved_processor_overrides(config, device: str, stats: dict | None,
                              rename_map: dict[str, str]) -> tuple[dict, dict]:
    """(preprocessor_overrides, postprocessor_overrides) for make_pre_post_processors with a
    checkpoint's saved pipelines: our device, the policy's features and norm map, our rename map,
    and `stats` (dataset stats) when given, else the checkpoint's own saved stats are kept."""
    features = {**config.input_features, **config.output_features}
    normalizer = {"features": features, "norm_map": config.normalization_mapping}
    unnormalizer = {"features": dict(config.output_features), "norm_map": config.normalization_mapping}
    if stats is not None:
        normalizer["stats"] = stats
        unnormalizer["stats"] = stats
    pre = {
        "device_processor": {"device": device},
        "normalizer_processor": normalizer,
        "rename_observations_processor": {"rename_map": dict(rename_map)},
    }
    return pre, {"unnormalizer_processor": unnormalizer}


def check_normalizer_covers(pipeline, source: str, keys=(STATE_KEY, ACTION_KEY)) -> None:
    """Raise unless the pipeline's (un)normaliser has features AND stats for every key it must
    normalise (IDENTITY-mapped keys excepted): otherwise values would pass through raw."""
    from lerobot.configs import NormalizationMode

    steps = [s for s in pipeline.steps if type(s).__name__ in
             ("NormalizerProcessorStep", "UnnormalizerProcessorStep")]
    if len(steps) != 1:
        raise RuntimeError(f"{source}: expected one (un)normaliser step in {pipeline.name}")
    step = steps[0]
    for key in keys:
        feature = step.features.get(key)
        if feature is None:
            if key == STATE_KEY and type(step).__name__ == "UnnormalizerProcessorStep":
                continue  # the post-processor only sees actions
            raise ValueError(
                f"{source}: the saved {type(step).__name__} has no feature {key!r} (its features: "
                f"{sorted(step.features)}): {key} would pass through unnormalised; load it with "
                "dataset stats (backbone entry stats='dataset') or fix the checkpoint's processor"
            )
        mode = step.norm_map.get(feature.type, NormalizationMode.IDENTITY)
        if mode == NormalizationMode.IDENTITY:
            continue
        if key not in step._tensor_stats or not step._tensor_stats[key]:
            raise ValueError(
                f"{source}: the saved {type(step).__name__} has no {mode.value} stats for "
                f"{key!r}: pass dataset stats (backbone entry stats='dataset')"
            )


def stats_fingerprint(stats: dict, keys=(STATE_KEY, ACTION_KEY)) -> str:
    """12 hex chars over the state/action normalisation stats (sorted, float64 bytes)."""
    hasher = hashlib.sha256()
    for key in keys:
        for name in sorted(stats.get(key, {})):
            value = stats[key][name]
            array = value.detach().cpu().double().numpy() if torch.is_tensor(value) else np.asarray(value, dtype=np.float64)
            hasher.update(f"{key}.{name}".encode())
            hasher.update(np.ascontiguousarray(array).tobytes())
    return hasher.hexdigest()[:12]


def normalizer_stats(pipeline) -> dict:
    """The stats the pipeline's (un)normaliser actually uses, {key: {stat: tensor}}."""
    for step in pipeline.steps:
        if type(step).__name__ in ("NormalizerProcessorStep", "UnnormalizerProcessorStep"):
            return step._tensor_stats
    raise RuntimeError(f"{pipeline.name} has no (un)normaliser step")


def download_command(repo_id: str, revision: str | None = None, include: tuple[str, ...] = (),
                     repo_type: str = "model", files: tuple[str, ...] = ()) -> str:
    """The `hf download` line that puts `repo_id` (or just `files` of it) into the Hugging Face
    cache graftbench reads. One owner for every fix message (policies, datasets, timm weights)."""
    parts = ["hf download"]
    if repo_type != "model":
        parts.append(f"--repo-type {repo_type}")
    parts += [repo_id, *files]
    if revision:
        parts.append(f"--revision {revision}")
    if include:
        parts.append("--include " + " ".join(f'"{p}"' for p in include))
    return " ".join(parts)


def hub_artifact(kind: str, repo_id: str, files: tuple[str, ...], needed_by: str,
                 revision: str | None = None, include: tuple[str, ...] = (), note: str = ""):
    """An Artifact for `files` of `repo_id` at `revision` in the Hugging Face cache."""
    from huggingface_hub import constants

    from bench.artifacts import Artifact

    missing = [f for f in files if cached_file(repo_id, f, revision) is None]
    if missing:
        at = f"@{revision}" if revision else ""
        where = f"{constants.HF_HUB_CACHE} lacks {repo_id}{at}: {', '.join(missing)}"
        fix = download_command(repo_id, revision, include)
    else:
        where, fix = str(cached_file(repo_id, files[0], revision).parent), ""
    return Artifact(kind, repo_id, needed_by, not missing, where, fix, revision, note)


def require_present(artifacts) -> None:
    """Offline, raise BackboneUnavailable (one line, with the fix) for the first missing one;
    online, let LeRobot download what is missing."""
    from backbones.base import BackboneUnavailable

    if not hub_offline():
        return
    for a in artifacts:
        if not a.present:
            note = f" ({a.note})" if a.note else ""
            raise BackboneUnavailable(
                f"{a.kind} {a.repo_id} for {a.needed_by} is not in the Hugging Face cache and the "
                f"hub is offline ({a.where}); fix: `{a.fix}` on a networked machine with the same "
                f"HF_HOME{note}"
            )


# LIBERO's two cameras (agent view, wrist), in the order the suites give them.
LIBERO_CAMERAS = ("observation.images.image", "observation.images.wrist_image")
# Camera names released checkpoints use for those two views, tried in order (docs/HUB_FACTS.md):
# LIBERO's own; pi05_base's DROID-style keys; LeRobot's combined-LIBERO ports (image, image2);
# smolvla_base's SO-100 slots and smolvla_libero (camera1, camera2). A slot of the checkpoint
# that no layout fills (pi05_base's right wrist, smolvla_base's camera3) is dropped.
CAMERA_LAYOUTS = (
    LIBERO_CAMERAS,
    ("observation.images.base_0_rgb", "observation.images.left_wrist_0_rgb"),
    ("observation.images.image", "observation.images.image2"),
    ("observation.images.camera1", "observation.images.camera2"),
)


def libero_rename_map(image_keys, policy_type: str) -> dict[str, str]:
    """{LIBERO camera: checkpoint camera} by the first layout the checkpoint has both slots of;
    a one-line error naming the checkpoint's cameras when none fits."""
    from backbones.base import BackboneUnavailable

    for layout in CAMERA_LAYOUTS:
        if all(key in image_keys for key in layout):
            return dict(zip(LIBERO_CAMERAS, layout))
    raise BackboneUnavailable(
        f"{policy_type} checkpoint cameras {list(image_keys)} match none of the known layouts "
        f"{[list(layout) for layout in CAMERA_LAYOUTS]}; add its layout to "
        "backbones.hub.CAMERA_LAYOUTS (agent view first, then wrist)"
    )


def saved_normalizer_stats(source: str, revision: str | None = None) -> dict | None:
    """The stats a checkpoint's saved pre-processor normalises with, {key: {stat: tensor}}, read
    from its policy_preprocessor.json's normaliser state file (local folder or HF cache)."""
    import json

    from safetensors.torch import load_file

    def find(filename: str) -> Path | None:
        local = Path(source) / filename
        return local if local.is_file() else cached_file(source, filename, revision)

    config_path = find("policy_preprocessor.json")
    if config_path is None:
        return None
    steps = json.loads(config_path.read_text()).get("steps", [])
    files = [s.get("state_file") for s in steps if s.get("registry_name") == "normalizer_processor"]
    state_path = find(files[0]) if files and files[0] else None
    if state_path is None:
        return None
    stats: dict = {}
    for flat, tensor in load_file(str(state_path)).items():
        key, stat = flat.rsplit(".", 1)
        stats.setdefault(key, {})[stat] = tensor
    return stats
