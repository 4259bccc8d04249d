"""The one writer of every LeRobotDataset graftbench generates (the synthetic suites, the custom
world, the simulator's demonstrations): LeRobot's own `LeRobotDataset.create`, images in the
parquet."""

from __future__ import annotations

import shutil
from pathlib import Path


def write_dataset(root: str | Path, repo: str, spec: dict, robot_type: str, fps: int,
                  stream) -> None:
    """Episodes `stream` of (task text, frames) as a LeRobotDataset at `root` (images stored in
    the parquet, not as video): the one writer of every generated world.

    `spec`: LeRobot features; each frame a {feature: value} dict without "task"."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    import datasets

    bars = datasets.is_progress_bar_enabled()
    datasets.disable_progress_bars()  # one "Map" bar per episode otherwise
    try:
        ds = LeRobotDataset.create(repo, fps=fps, features=spec, root=root,
                                   robot_type=robot_type, use_videos=False)
        for text, frames in stream:
            for frame in frames:
                ds.add_frame({**frame, "task": text})
            ds.save_episode()
        ds.finalize()
    finally:
        if bars:
            datasets.enable_progress_bars()
    shutil.rmtree(Path(root) / "images", ignore_errors=True)  # PNG staging, now in parquet
