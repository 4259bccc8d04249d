"""The real LIBERO suites as LeRobot datasets, found in a local root or the Hugging Face cache.

Assumption (stated, not verified offline): the suites are LeRobot's image-format ports
`lerobot/libero_{spatial,object,goal,10}_image` (LeRobot's own scripts use
`lerobot/libero_10_image`), with features observation.images.image and
observation.images.wrist_image (256x256 RGB, dtype "image"), observation.state (8), action (7)
and one task string per episode, codebase v3.0 (what lerobot 0.6.1 reads). Another port with the
same features works through `root` or GRAFTBENCH_LIBERO_ROOT; a port with other names fails
validation with a one-line SuiteUnavailable.
"""

from __future__ import annotations

import os
from pathlib import Path

from bench.suites.base import (
    ACTION_KEY,
    IMAGE_KEYS,
    LIBERO_ACTION_DIM,
    LIBERO_STATE_DIM,
    STATE_KEY,
    SuiteUnavailable,
)

LIBERO_REPO_IDS = {
    "spatial": "lerobot/libero_spatial_image",
    "object": "lerobot/libero_object_image",
    "goal": "lerobot/libero_goal_image",
    "10": "lerobot/libero_10_image",
}
ROOT_ENV = "GRAFTBENCH_LIBERO_ROOT"
CAMERA_DTYPES = ("image", "video")


def hub_offline() -> bool:
    """True when HF_HUB_OFFLINE asks for no network (read at call time, not import time)."""
    return os.environ.get("HF_HUB_OFFLINE", "").strip().lower() in ("1", "true", "yes", "on")


def lerobot_home() -> Path:
    """LeRobot's dataset cache ($HF_LEROBOT_HOME, default $HF_HOME/lerobot)."""
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME)


def candidate_roots(repo_id: str, root: str | Path | None = None) -> list[Path]:
    """Folders that may hold `repo_id`, in the order they are tried."""
    org, name = repo_id.split("/")
    bases = [Path(root)] if root is not None else []
    if os.environ.get(ROOT_ENV):
        bases.append(Path(os.environ[ROOT_ENV]))
    found = []
    for base in bases:
        found += [base, base / repo_id, base / name]
    home = lerobot_home()
    found.append(home / repo_id)
    # LeRobot's revision-safe snapshot cache: $HF_LEROBOT_HOME/hub/datasets--org--name/snapshots/*
    snapshots = home / "hub" / f"datasets--{org}--{name}" / "snapshots"
    if snapshots.is_dir():
        found += sorted(snapshots.iterdir(), key=lambda p: p.stat().st_mtime, reverse=True)
    return found


def locate(repo_id: str, root: str | Path | None = None) -> Path | None:
    """The first candidate folder holding a LeRobot dataset (meta/info.json), else None."""
    for path in candidate_roots(repo_id, root):
        if (path / "meta" / "info.json").is_file():
            return path
    return None


def validate_features(features: dict, repo_id: str) -> None:
    """Raise SuiteUnavailable (one line) unless `features` has LIBERO's cameras, state, action."""
    fix = "use a LIBERO port with LeRobot's LIBERO feature names (e.g. lerobot/libero_*_image)"
    for camera in IMAGE_KEYS:
        spec = features.get(camera)
        if spec is None:
            raise SuiteUnavailable(f"{repo_id}: missing camera feature {camera!r}; {fix}")
        if spec.get("dtype") not in CAMERA_DTYPES or len(spec.get("shape", ())) != 3:
            raise SuiteUnavailable(
                f"{repo_id}: feature {camera!r} is {spec.get('dtype')} {tuple(spec.get('shape', ()))}"
                f", expected an RGB image or video (H, W, 3); {fix}"
            )
    for key, dim in ((STATE_KEY, LIBERO_STATE_DIM), (ACTION_KEY, LIBERO_ACTION_DIM)):
        spec = features.get(key)
        if spec is None:
            raise SuiteUnavailable(f"{repo_id}: missing feature {key!r} ({dim} dims); {fix}")
        if tuple(spec.get("shape", ())) != (dim,):
            raise SuiteUnavailable(
                f"{repo_id}: feature {key!r} has shape {tuple(spec.get('shape', ()))}, "
                f"expected ({dim},); {fix}"
            )
    if "task_index" not in features:
        raise SuiteUnavailable(f"{repo_id}: missing feature 'task_index' (task strings); {fix}")


def image_shape_chw(spec: dict) -> tuple[int, int, int]:
    """(3, H, W) from a LeRobot image feature spec stored (H, W, C) or (C, H, W)."""
    shape = tuple(int(s) for s in spec["shape"])
    names = [str(n).lower() for n in (spec.get("names") or [])]
    channel_last = (names and names[-1] in ("channel", "channels", "rgb", "c")) or shape[-1] == 3
    h, w, c = shape if channel_last else (shape[1], shape[2], shape[0])
    return (c, h, w)


def open_dataset(name: str, root: str | Path | None = None):
    """LeRobotDataset of LIBERO suite `name`, validated; SuiteUnavailable if absent or malformed.

    Offline (HF_HUB_OFFLINE=1) a cache miss fails at once, without touching the network.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if name not in LIBERO_REPO_IDS:
        raise ValueError(f"unknown LIBERO suite {name!r}; choose one of {sorted(LIBERO_REPO_IDS)}")
    repo_id = LIBERO_REPO_IDS[name]
    local = locate(repo_id, root)
    if local is None and hub_offline():
        where = [str(p) for p in ([Path(root)] if root else []) + [lerobot_home()]]
        raise SuiteUnavailable(
            f"LIBERO suite {name!r}: dataset {repo_id} not found under {', '.join(where)} and "
            f"HF_HUB_OFFLINE=1; fix: `hf download --repo-type dataset {repo_id}` on a networked "
            f"machine into {lerobot_home()}, or point {ROOT_ENV} at a local copy"
        )
    try:
        ds = LeRobotDataset(repo_id, root=local)  # root=None: download into LeRobot's cache
    except Exception as err:  # network, auth, format version: one actionable line
        raise SuiteUnavailable(
            f"LIBERO suite {name!r}: could not load {repo_id} ({type(err).__name__}: "
            f"{str(err).splitlines()[0] if str(err) else ''}); fix: download it with "
            f"`hf download --repo-type dataset {repo_id}` or set {ROOT_ENV}"
        ) from err
    validate_features(ds.features, repo_id)
    return ds
