"""A LeRobotDataset (v3) of your own as a suite: `--dataset NAME=PATH_OR_REPO_ID`.

`dataset_facts` reads only meta/ (cameras, state and action widths, fps, whether it has tasks), so
the grid checks a policy x dataset pair at collection, before anything trains or decodes;
`load_user_suite` reads the data through `LeRobotDataset` and `suite_from_dataset`, as the
built-in suites are read.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ondisk.libero_format import ACTION_KEY, STATE_KEY
from bench.suites.base import SuiteUnavailable

IMAGES_IN_MEMORY_MAX = 20_000  # frames x cameras decoded once and kept; beyond: on demand


@dataclass(frozen=True)
class DatasetFacts:
    source: str  # as given (path or repo id)
    root: Path  # the local folder holding meta/info.json
    repo_id: str
    cameras: tuple[str, ...]  # image/video features, in the dataset's order
    state_dim: int | None  # None: no observation.state
    action_dim: int | None
    fps: int
    has_tasks: bool  # a task_index column and meta/tasks.parquet
    video: bool


def locate_dataset(source: str, name: str | None = None) -> Path:
    """The local folder of a dataset given as a path or a repo id (LeRobot's home, HF cache);
    `name`: the suite name it was given under, for the message (--dataset NAME=SOURCE)."""
    local = Path(source).expanduser()
    if (local / "meta" / "info.json").is_file():
        return local.resolve()
    from bench.suites import libero

    if not local.exists() and source.count("/") == 1:
        found = libero.locate(source)
        if found is not None:
            return found
    given = f"{name}={source}" if name else source
    raise SuiteUnavailable(
        f"--dataset {given}: no LeRobotDataset there (no meta/info.json); give the dataset's "
        f"folder, or a repo id in the cache (`{libero.download_command(source)}`)"
        if not local.exists() and source.count("/") == 1 else
        f"--dataset {given}: no LeRobotDataset there (no meta/info.json); give the folder that "
        "holds meta/ and data/")


def dataset_facts(source: str, name: str | None = None) -> DatasetFacts:
    root = locate_dataset(source, name)
    info = json.loads((root / "meta" / "info.json").read_text())
    feats = info.get("features", {})
    cameras = tuple(k for k, f in feats.items() if f.get("dtype") in ("image", "video"))

    def width(key):
        shape = feats.get(key, {}).get("shape")
        return int(shape[0]) if shape else None

    return DatasetFacts(
        source=source, root=root, repo_id=info.get("repo_id") or f"local/{root.name}",
        cameras=cameras, state_dim=width(STATE_KEY), action_dim=width(ACTION_KEY),
        fps=int(info.get("fps", 0)),
        has_tasks="task_index" in feats and (root / "meta" / "tasks.parquet").is_file(),
        video=any(feats[c]["dtype"] == "video" for c in cameras))


def check_dataset(name: str, facts: DatasetFacts) -> None:
    """What every suite needs of a dataset: cameras, state, action, tasks (one-line errors)."""
    where = f"--dataset {name}={facts.source}"
    if not facts.cameras:
        raise ValueError(f"{where}: no image or video feature (its features have no camera); "
                         "graftbench grafts vision encoders: give a dataset with cameras")
    for key, dim in ((STATE_KEY, facts.state_dim), (ACTION_KEY, facts.action_dim)):
        if dim is None:
            raise ValueError(f"{where}: no {key!r} feature; rename your state/action columns to "
                             f"LeRobot's {STATE_KEY!r} and {ACTION_KEY!r}")
    if not facts.has_tasks:
        raise ValueError(f"{where}: no task column (task_index and meta/tasks.parquet); held-out "
                         "episodes are drawn per task: record each episode with a task string")


def load_user_suite(name: str, source: str):
    """Suite `name` from the dataset at `source`, every camera of it, read by LeRobotDataset."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from bench.suites import suite_from_dataset

    facts = dataset_facts(source, name)
    check_dataset(name, facts)
    ds = LeRobotDataset(facts.repo_id, root=facts.root)
    frames = int(ds.meta.total_frames)
    in_memory = not facts.video and frames * len(facts.cameras) <= IMAGES_IN_MEMORY_MAX
    return suite_from_dataset(name, ds, images_in_memory=in_memory, camera_keys=facts.cameras)
