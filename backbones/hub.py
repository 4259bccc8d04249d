"""What the adapters need from the Hugging Face cache and LeRobot's saved processors.

Cache look-ups and fix lines: ondisk.hubcache (read from there). One owner here for: the overrides that make a
checkpoint's SAVED processor pipeline fit the policy we built (LeRobot's own lerobot_train.py
~356-377 passes the same ones), and the check that the resulting normaliser covers the state and
action it will see (a hub `policy_preprocessor.json` may carry `"features": {}`, which makes the
normaliser pass the state through untouched without a word).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Callable, Iterator

import torch

from backbones.base import BackboneUnavailable
from ondisk.hubcache import cached_file, download_command, hub_offline
from ondisk.libero_format import ACTION_KEY, STATE_KEY


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


def require_present(artifacts) -> None:
    """Offline, raise BackboneUnavailable (one line, with the fix) for the first missing one;
    online, let LeRobot download what is missing."""
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


@contextlib.contextmanager
def errors_as_unavailable(repo_id: str, artifacts: Callable[[], list], what: str = "",
                          local: tuple[str, ...] = ()) -> Iterator[None]:
    """Hub and auth errors while loading (online: a gated tokenizer, a missing revision;
    offline: a file the cache lacks) as one BackboneUnavailable line naming the fix of each of
    `artifacts()`. Errors loading local folders (`repo_id` and every `local` path) pass as they
    are: their own message is the clearest."""
    from huggingface_hub.errors import HfHubHTTPError

    try:
        yield
    except (HfHubHTTPError, OSError) as error:  # transformers and LeRobot raise OSError subclasses
        if all(Path(p).is_dir() for p in (repo_id, *local)):
            raise
        fixes = "; ".join(f"`{a.fix or download_command(a.repo_id, a.revision)}`"
                          + (f" ({a.note})" if a.note else "") for a in artifacts())
        reason = " ".join(str(error).split())[:240]
        raise BackboneUnavailable(
            f"could not load {repo_id}{what} ({type(error).__name__}: {reason}); fix: "
            f"{fixes or 'check the network and your hub token'} on a networked machine with the "
            "same HF_HOME, or pass a local checkpoint folder"
        ) from error
