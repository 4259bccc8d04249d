"""The real LIBERO suites as LeRobot datasets, found in a local root, LeRobot's cache or the
Hugging Face hub cache (where `hf download --repo-type dataset REPO` puts them).

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

from ondisk.hubcache import hub_offline
from ondisk.artifacts import Artifact
from ondisk.libero_format import (
    ACTION_KEY, IMAGE_KEYS, LIBERO_ACTION_DIM, LIBERO_STATE_DIM, LIBERO_SUITES, STATE_KEY,
)
from bench.suites.base import SuiteUnavailable

LIBERO_REPO_IDS = {name: s.repo_id for name, s in LIBERO_SUITES.items()}
# Hub revision each suite is pinned to; None: no pin (the hub cache's refs/main, LeRobot's default).
LIBERO_REVISIONS: dict[str, str | None] = {name: None for name in LIBERO_REPO_IDS}
ROOT_ENV = "GRAFTBENCH_LIBERO_ROOT"
CAMERA_DTYPES = ("image", "video")
REASON_CHARS = 300


def lerobot_home() -> Path:
    """LeRobot's dataset cache ($HF_LEROBOT_HOME, default $HF_HOME/lerobot)."""
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME)


def hub_cache() -> Path:
    """The Hugging Face hub cache `hf download` writes to (huggingface_hub's HF_HUB_CACHE)."""
    from huggingface_hub import constants

    return Path(constants.HF_HUB_CACHE)


def hub_snapshots(repo_id: str, cache: Path, revision: str | None = None) -> list[Path]:
    """Snapshot folders of dataset `repo_id` in hub-layout `cache`: the one refs/<revision or
    main> names first, then the others newest first; a pinned revision admits only its own."""
    repo = cache / f"datasets--{repo_id.replace('/', '--')}"
    snapshots = repo / "snapshots"
    if not snapshots.is_dir():
        return []
    ref = repo / "refs" / (revision or "main")
    sha = ref.read_text().strip() if ref.is_file() else revision  # a pin may be a commit sha
    named = [snapshots / sha] if sha and (snapshots / sha).is_dir() else []
    if revision is not None:
        return named
    others = sorted((p for p in snapshots.iterdir() if p not in named),
                    key=lambda p: p.stat().st_mtime, reverse=True)
    return named + others


def places_looked(repo_id: str, root: str | Path | None = None) -> list[Path]:
    """The folders searched for `repo_id`, as a person would check them (no snapshot expansion)."""
    places = [Path(root)] if root is not None else []
    if os.environ.get(ROOT_ENV):
        places.append(Path(os.environ[ROOT_ENV]))
    home = lerobot_home()
    places += [home / repo_id, home / "hub", hub_cache()]
    return list(dict.fromkeys(places))


def candidate_roots(repo_id: str, root: str | Path | None = None,
                    revision: str | None = None) -> list[Path]:
    """Folders that may hold `repo_id`, in the order they are tried."""
    name = repo_id.split("/")[1]
    bases = [Path(root)] if root is not None else []
    if os.environ.get(ROOT_ENV):
        bases.append(Path(os.environ[ROOT_ENV]))
    found = []
    for base in bases:
        found += [base, base / repo_id, base / name]
    home = lerobot_home()
    found.append(home / repo_id)
    # LeRobot's revision-safe snapshot cache ($HF_LEROBOT_HOME/hub), then the HF hub cache that
    # `hf download --repo-type dataset` fills; both have the datasets--org--name/snapshots layout.
    for cache in dict.fromkeys((home / "hub", hub_cache())):
        found += hub_snapshots(repo_id, cache, revision)
    return found


def locate(repo_id: str, root: str | Path | None = None,
           revision: str | None = None) -> Path | None:
    """The first candidate folder holding a LeRobot dataset (meta/info.json), else None."""
    for path in candidate_roots(repo_id, root, revision):
        if (path / "meta" / "info.json").is_file():
            return path
    return None


def download_command(repo_id: str, revision: str | None = None) -> str:
    """The shell command that puts `repo_id` in the HF hub cache, where locate() finds it."""
    from ondisk.hubcache import download_command as hf_download

    return hf_download(repo_id, revision, repo_type="dataset")


def _repo_id(name: str) -> str:
    if name not in LIBERO_REPO_IDS:
        raise ValueError(f"unknown LIBERO suite {name!r}; choose one of {sorted(LIBERO_REPO_IDS)}")
    return LIBERO_REPO_IDS[name]


def dataset_artifact(name: str, root: str | Path | None = None,
                     revision: str | None = None) -> Artifact:
    """The dataset LIBERO suite `name` reads: present when locate() finds its meta/info.json."""
    repo_id = _repo_id(name)
    revision = revision if revision is not None else LIBERO_REVISIONS.get(name)
    local = locate(repo_id, root, revision)
    where = str(local) if local else "not in " + ", ".join(map(str, places_looked(repo_id, root)))
    return Artifact(kind="dataset", repo_id=repo_id, needed_by=f"suite {name}",
                    present=local is not None, where=where,
                    fix="" if local else download_command(repo_id, revision), revision=revision)


def one_line(text: str, limit: int = REASON_CHARS) -> str:
    """`text` with whitespace runs (newlines included) collapsed to one space, cut at `limit`."""
    flat = " ".join(text.split())
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


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


def open_dataset(name: str, root: str | Path | None = None, revision: str | None = None):
    """LeRobotDataset of LIBERO suite `name`, validated; SuiteUnavailable if absent or malformed.

    Offline (HF_HUB_OFFLINE=1) a cache miss fails at once, without touching the network.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    repo_id = _repo_id(name)
    revision = revision if revision is not None else LIBERO_REVISIONS.get(name)
    local = locate(repo_id, root, revision)
    fix = (f"fix: `{download_command(repo_id, revision)}` (needs network; fills the HF hub cache "
           f"{hub_cache()}), or `{download_command(repo_id, revision)} --local-dir "
           f"{lerobot_home() / repo_id}`, or point {ROOT_ENV} at a local copy")
    if local is None and hub_offline():
        where = ", ".join(map(str, places_looked(repo_id, root)))
        raise SuiteUnavailable(f"LIBERO suite {name!r}: dataset {repo_id} not found under {where} "
                               f"and HF_HUB_OFFLINE=1; {fix}")
    try:
        # root=None: LeRobot downloads into its own cache ($HF_LEROBOT_HOME/hub)
        ds = LeRobotDataset(repo_id, root=local, revision=revision)
    except Exception as err:  # network, auth, format version: one actionable line
        raise SuiteUnavailable(f"LIBERO suite {name!r}: could not load {repo_id} "
                               f"({type(err).__name__}: {one_line(str(err))}); {fix}") from err
    validate_features(ds.features, repo_id)
    return ds
