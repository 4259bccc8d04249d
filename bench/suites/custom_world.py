"""A small non-LIBERO world: another robot's layout with the tiny suites' planted visual signal.

What "your own data" looks like to graftbench when it is not LIBERO: a LeRobotDataset (v3) with
cameras `observation.images.front` and `observation.images.wrist`, a 6-D joint-like state and a
6-D action, 30 fps. The scenes and the scripted expert are the spatial suite's
(bench.suites.synthetic, unchanged): block and destination positions are drawn in the images and
NOT in the state, so predicting the action needs vision. Only the layout differs:

- state (6): eef x, y, z, two wrist angles (small noise, as LIBERO's axis-angle), gripper opening;
- action (6): delta x, y, z, two wrist-angle deltas (0), gripper (-1 open, +1 close).

Tests build it with `generate_world(root, ...)` and point `--dataset NAME=root` at it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.suites import synthetic
from ondisk.lerobot_dataset import write_dataset
from ondisk.libero_format import ACTION_KEY, IMAGE_KEYS, STATE_KEY

FRONT, WRIST = "observation.images.front", "observation.images.wrist"
CAMERAS = (FRONT, WRIST)
STATE_DIM = ACTION_DIM = 6
FPS = 30
ROBOT = "graftbench_arm6"


def features(image_size: int = synthetic.IMAGE_SIZE) -> dict:
    image = {"dtype": "image", "shape": (image_size, image_size, 3),
             "names": ["height", "width", "channel"]}
    return {
        FRONT: dict(image), WRIST: dict(image),
        STATE_KEY: {"dtype": "float32", "shape": (STATE_DIM,),
                    "names": ["x", "y", "z", "wrist_flex", "wrist_roll", "gripper"]},
        ACTION_KEY: {"dtype": "float32", "shape": (ACTION_DIM,),
                     "names": ["dx", "dy", "dz", "dwrist_flex", "dwrist_roll", "gripper"]},
    }


def to_arm6(frame: dict) -> dict:
    """A spatial-suite frame (LIBERO layout) in this world's layout."""
    state, action = frame[STATE_KEY], frame[ACTION_KEY]
    return {FRONT: frame[IMAGE_KEYS[0]], WRIST: frame[IMAGE_KEYS[1]],
            STATE_KEY: np.r_[state[:5], state[6]].astype(np.float32),
            ACTION_KEY: np.r_[action[:5], action[6]].astype(np.float32)}


def generate_world(root: str | Path, seed: int = 0, tasks: int = 2, episodes_per_task: int = 10,
                   min_len: int = 20, max_len: int = 40) -> Path:
    """Write the world as a LeRobotDataset at `root` (must not exist); returns `root`.
    Tasks are the spatial suite's first `tasks` (colour x destination) instructions."""
    rng = np.random.default_rng([seed, 6])

    def stream():
        for task in range(tasks):
            for _ in range(episodes_per_task):
                text, frames = synthetic.spatial_episode(rng, task, min_len, max_len)
                yield text, [to_arm6(frame) for frame in frames]

    write_dataset(root, f"local/{ROBOT}_world", features(), ROBOT, FPS, stream())
    return Path(root)
