"""LeRobot's LIBERO dataset format: the feature keys and dims of the public LeRobot LIBERO
datasets, and the feature spec of the LIBERO-format datasets graftbench writes."""

from __future__ import annotations

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
