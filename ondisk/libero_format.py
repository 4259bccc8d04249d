"""LIBERO as graftbench meets it: its suites (their LeRobot datasets, LIBERO benchmarks and
episode limits), the feature keys and dims of the public LeRobot LIBERO datasets, and the
feature spec of the LIBERO-format datasets graftbench writes."""

from __future__ import annotations

from dataclasses import dataclass

# LIBERO's feature names (the public LeRobot LIBERO datasets).
IMAGE_KEYS = ("observation.images.image", "observation.images.wrist_image")
STATE_KEY = "observation.state"
ACTION_KEY = "action"
LIBERO_STATE_DIM = 8
LIBERO_ACTION_DIM = 7


def libero_features(image_size: int) -> dict:
    """LeRobot feature spec of a LIBERO-format dataset written here (synthetic or simulated):
    LIBERO's names and layouts, square images (H, W, C) stored as "image" (not video)."""
    image = {"dtype": "image", "shape": (image_size, image_size, 3),
             "names": ["height", "width", "channel"]}
    return {
        IMAGE_KEYS[0]: dict(image),
        IMAGE_KEYS[1]: dict(image),
        STATE_KEY: {"dtype": "float32", "shape": (LIBERO_STATE_DIM,),
                    "names": ["x", "y", "z", "ax", "ay", "az", "gripper_left", "gripper_right"]},
        ACTION_KEY: {"dtype": "float32", "shape": (LIBERO_ACTION_DIM,),
                     "names": ["dx", "dy", "dz", "dax", "day", "daz", "gripper"]},
    }


@dataclass(frozen=True)
class LiberoSuite:
    """One LIBERO suite: its LeRobot dataset, its benchmark in LIBERO, its episode limit."""

    name: str  # graftbench's suite name
    repo_id: str  # the LeRobot image-format port on the hub
    benchmark: str  # LIBERO's task-suite name (the simulator's scenes)
    max_steps: int  # control steps per rollout episode: LeRobot's LiberoEnv limit


# Adding a LIBERO suite is one entry (its tiny stand-in: bench.suites.synthetic.SUITE_PARAMS;
# its simulated one: bench.sim.demos.DEFAULT_SPECS).
LIBERO_SUITES: dict[str, LiberoSuite] = {s.name: s for s in (
    LiberoSuite("spatial", "lerobot/libero_spatial_image", "libero_spatial", 280),
    LiberoSuite("object", "lerobot/libero_object_image", "libero_object", 280),
    LiberoSuite("goal", "lerobot/libero_goal_image", "libero_goal", 300),
    LiberoSuite("10", "lerobot/libero_10_image", "libero_10", 520),
)}
