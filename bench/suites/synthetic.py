"""Small LIBERO-format suites generated offline, with a visual signal planted in the images.

The world is a table seen from above: world xy in [-WORLD_HALF, WORLD_HALF] maps linearly onto
the 64x64 agent-view image (`world_to_pixel`). An end-effector (eef) follows a scripted
proportional controller through two phases: reach the object, then carry it to a destination.
The positions of object and destination are drawn in the image and are NOT in the state (state
holds only the eef pose and gripper), so predicting the action needs vision:

- spatial: a red and a blue block, a plate and a bowl, one in each corner slot (a random
  permutation). The task string names which block goes where (2 colours x 2 destinations = 4
  tasks).
- object: one object of 4 types (red disk, green square, blue triangle, yellow cross) in one of
  four inner slots; 4 identical baskets in the corners. Task k sends object type i to basket
  (i + k) % 4, so identity (read from the image) and the task string together decide the
  destination.

Why slots, large objects and an event-driven expert (generator 5; docs/TINY_SMOLVLA.md has the
numbers): the tiny policies' few image tokens (SmolVLA 2x2 per camera, pi0.5 4x4) each see one
slot whole, so what a token shows is one of a few categories and a single Linear from pooled
features can reach the native policy's code; and the gripper closes / opens when the eef reaches
its goal (not at a hidden time), so the action is a function of state and images and the part a
blind policy cannot know is the visual part. Under generator 2 (random positions, small objects,
a clock-driven grasp) the tiny SmolVLA's native policy beat a blind graft by 4% and no graft
could do better than blind.

Feature names, dtypes and shapes follow LeRobot's LIBERO datasets (images stored as PNG "image"
features, not video: decoding video needs system FFmpeg). State is LIBERO's 8 dims (eef xyz,
axis-angle, two gripper fingers), action its 7 (delta xyz, delta axis-angle, gripper -1 open /
+1 close). Everything is drawn from `seed`.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from bench.progress import Progress, ProgressSink
from ondisk.filelock import exclusive, try_exclusive
from ondisk.paths import build_dataset_dir, cache_dir
from ondisk.libero_format import ACTION_KEY, IMAGE_KEYS, STATE_KEY, libero_features
from ondisk.lerobot_dataset import write_dataset

# Bump when a change to this file changes generated data: it is part of the cache key.
GENERATOR_VERSION = "5"
IMAGE_SIZE = 64
FPS = 10
WORLD_HALF = 0.25  # world xy in [-0.25, 0.25] m covers the agent view
STEP = 0.06  # eef displacement (m) per unit action per frame
GAIN_RANGE = 0.25  # distance (m) at which the proportional action saturates at 1
GRIPPER_OPEN = 0.04
REACH_TOL = 0.02  # m: the eef grasps / releases within this distance of its goal
RELEASE_FRAMES = 3

TABLE = (150, 128, 104)
SPATIAL_TASKS = [
    ("red", "plate"), ("red", "bowl"), ("blue", "plate"), ("blue", "bowl"),
]
COLOURS = {
    "red": (220, 30, 30), "blue": (30, 60, 220), "green": (30, 190, 60), "yellow": (230, 210, 30),
    "plate": (245, 245, 245), "bowl": (110, 60, 30), "basket": (70, 70, 70), "gripper": (25, 25, 25),
}
OBJECT_TYPES = ("red disk", "green square", "blue triangle", "yellow cross")
OBJECT_TASKS = (
    "put the object in its matching basket",
    "put the object in the basket one step clockwise from its match",
    "put the object in the basket opposite its match",
    "put the object in the basket one step counter-clockwise from its match",
)
# Basket corners, clockwise from top-left (row grows downwards: y = -0.19 is the top).
BASKETS = np.array([[-0.19, -0.19], [0.19, -0.19], [0.19, 0.19], [-0.19, 0.19]])
# Slots: pixel 8 / 56 (spatial, corners) and 24 / 40 (object, inner) are token centres of the
# tiny pi0.5's 4x4 grid, each inside one quadrant of the tiny SmolVLA's 2x2 grid.
SPATIAL_SLOTS = 0.1875 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
OBJECT_SLOTS = SPATIAL_SLOTS / 3
# Offset of an object within its slot, uniform in +-SLOT_JITTER (m). 0: the slot alone decides
# the position, so a token shows one of a few categories (generator 3 used 0.03).
SLOT_JITTER = 0.0

SUITE_PARAMS = {
    "spatial": dict(episodes_per_task=16, min_len=20, max_len=50),
    "object": dict(episodes_per_task=16, min_len=20, max_len=50),
}


def features() -> dict:
    """LeRobot feature spec of a generated suite (LIBERO names; images (H, W, C) like LIBERO)."""
    return libero_features(IMAGE_SIZE)


def world_to_pixel(xy: np.ndarray) -> np.ndarray:
    """(..., 2) world xy (m) -> (..., 2) agent-view pixel (col, row), float."""
    return (np.asarray(xy) + WORLD_HALF) / (2 * WORLD_HALF) * IMAGE_SIZE


def pixel_to_world(colrow: np.ndarray) -> np.ndarray:
    """(..., 2) agent-view pixel (col, row) -> (..., 2) world xy (m)."""
    return np.asarray(colrow) / IMAGE_SIZE * (2 * WORLD_HALF) - WORLD_HALF


# -- drawing ----------------------------------------------------------------------------------
def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[0:size, 0:size]
    return cols + 0.5, rows + 0.5


_COLS, _ROWS = _grid(IMAGE_SIZE)


def _draw(img: np.ndarray, shape: str, xy: np.ndarray, colour, r: float = 3.5) -> None:
    c, w = world_to_pixel(xy)
    dx, dy = _COLS - c, _ROWS - w
    if shape == "square":
        mask = (np.abs(dx) <= r) & (np.abs(dy) <= r)
    elif shape == "disk":
        mask = dx**2 + dy**2 <= r**2
    elif shape == "ring":
        mask = (dx**2 + dy**2 <= r**2) & (dx**2 + dy**2 >= (r - 2) ** 2)
    elif shape == "triangle":
        mask = (dy <= r) & (dy >= -r) & (np.abs(dx) <= (dy + r) / 2)
    elif shape == "cross":
        mask = ((np.abs(dx) <= 1.5) | (np.abs(dy) <= 1.5)) & (np.abs(dx) <= r) & (np.abs(dy) <= r)
    elif shape == "hollow":
        mask = (np.abs(dx) <= r) & (np.abs(dy) <= r) & ((np.abs(dx) > r - 1.2) | (np.abs(dy) > r - 1.2))
    else:
        raise ValueError(f"unknown shape {shape!r}")
    img[mask] = colour


def _render(items: list[tuple[str, np.ndarray, tuple, float]], eef: np.ndarray, q: float,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(agent view, wrist view), each (H, W, 3) uint8, from scene items and the eef pose."""
    scene = np.empty((IMAGE_SIZE, IMAGE_SIZE, 3), np.uint8)
    scene[:] = TABLE
    for shape, xy, colour, r in items:
        _draw(scene, shape, xy, colour, r)
    # Wrist view: a 2x zoom of the 32x32 patch under the eef, then the two fingers.
    half = IMAGE_SIZE // 4
    padded = np.empty((IMAGE_SIZE + 2 * half, IMAGE_SIZE + 2 * half, 3), np.uint8)
    padded[:] = TABLE
    padded[half:-half, half:-half] = scene
    c, w = np.clip(np.round(world_to_pixel(eef[:2])).astype(int), 0, IMAGE_SIZE)
    wrist = padded[w: w + 2 * half, c: c + 2 * half].repeat(2, 0).repeat(2, 1)
    gap = int(4 + q / GRIPPER_OPEN * 20)
    mid = IMAGE_SIZE // 2
    wrist[mid - 10: mid + 10, mid - gap - 4: mid - gap] = COLOURS["gripper"]
    wrist[mid - 10: mid + 10, mid + gap: mid + gap + 4] = COLOURS["gripper"]
    # Agent view: the gripper marker, larger when higher, hollow when open.
    agent = scene.copy()
    _draw(agent, "hollow" if q > GRIPPER_OPEN / 2 else "square", eef[:2], COLOURS["gripper"],
          2.5 + 8 * eef[2])
    noise = rng.integers(-3, 4, size=(2, IMAGE_SIZE, IMAGE_SIZE, 3))
    return tuple(np.clip(im.astype(np.int16) + n, 0, 255).astype(np.uint8)
                 for im, n in zip((agent, wrist), noise))


# -- scripted episodes ------------------------------------------------------------------------
def _rollout(rng, min_len: int, max_len: int, pick_xy, place_xy, items_of) -> list[dict]:
    """Scripted pick-and-place frames (LeRobot frame dicts); items_of(obj_xy) -> scene items.

    Event-driven: the gripper closes when the eef reaches the object and opens when it reaches
    the destination (both within REACH_TOL), so the action is a function of what the state and
    the images show, not of a hidden clock. The episode ends RELEASE_FRAMES after the release
    (held there until min_len), or at max_len."""
    # The eef starts anywhere over the table: a start near a fixed point would let the state
    # alone reveal the goal direction after a few frames (the policy could ignore the images).
    eef = np.r_[rng.uniform(-0.2, 0.2, 2), 0.20]
    q = GRIPPER_OPEN
    pick, place = np.r_[pick_xy, 0.03], np.r_[place_xy, 0.08]
    obj_xy = np.array(pick_xy, dtype=float)
    phase, released_for = "reach", 0
    frames = []
    for t in range(max_len):
        if phase == "reach" and np.linalg.norm(pick - eef) < REACH_TOL:
            phase = "carry"
        elif phase == "carry" and np.linalg.norm(place - eef) < REACH_TOL:
            phase = "release"
        if phase == "release":
            released_for += 1
            if released_for > RELEASE_FRAMES and t >= min_len:
                break
        carrying = phase == "carry"
        goal = pick if phase == "reach" else place
        if carrying:
            obj_xy = eef[:2].copy()
        agent, wrist = _render(items_of(obj_xy), eef, q, rng)
        action = np.zeros(7, np.float32)
        action[:3] = np.clip((goal - eef) / GAIN_RANGE, -1.0, 1.0)
        action[6] = 1.0 if carrying else -1.0
        state = np.r_[eef + rng.normal(0, 0.002, 3), rng.normal(0, 0.005, 3), q, -q]
        frames.append({IMAGE_KEYS[0]: agent, IMAGE_KEYS[1]: wrist,
                       STATE_KEY: state.astype(np.float32), ACTION_KEY: action})
        eef = eef + STEP * action[:3]
        q += 0.5 * ((0.0 if action[6] > 0 else GRIPPER_OPEN) - q)
    return frames


def spatial_episode(rng: np.random.Generator, task: int, min_len: int,
                    max_len: int) -> tuple[str, list[dict]]:
    """One spatial episode: (task string, frames)."""
    colour, dest = SPATIAL_TASKS[task]
    slots = SPATIAL_SLOTS[rng.permutation(4)]
    red, blue, plate, bowl = slots + rng.uniform(-SLOT_JITTER, SLOT_JITTER, (4, 2))
    blocks = {"red": red, "blue": blue}
    pick, place = blocks[colour], {"plate": plate, "bowl": bowl}[dest]

    other = "blue" if colour == "red" else "red"

    def items_of(obj_xy):
        held = {colour: obj_xy, other: blocks[other]}
        return [("disk", plate, COLOURS["plate"], 7.0), ("disk", bowl, COLOURS["bowl"], 7.0),
                ("square", held["red"], COLOURS["red"], 6.0),
                ("square", held["blue"], COLOURS["blue"], 6.0)]

    text = f"pick up the {colour} block and place it {'on' if dest == 'plate' else 'in'} the {dest}"
    return text, _rollout(rng, min_len, max_len, pick, place, items_of)


def object_destination(object_type: int, task: int) -> int:
    """Basket index (clockwise from top-left) for an object type under a task."""
    return (object_type + task) % 4


def object_episode(rng: np.random.Generator, task: int, object_type: int,
                   min_len: int, max_len: int) -> tuple[str, list[dict]]:
    """One object episode: (task string, frames)."""
    pick = OBJECT_SLOTS[rng.integers(4)] + rng.uniform(-SLOT_JITTER, SLOT_JITTER, 2)
    place = BASKETS[object_destination(object_type, task)]
    colour, shape = OBJECT_TYPES[object_type].split()

    def items_of(obj_xy):
        baskets = [("ring", b, COLOURS["basket"], 6.0) for b in BASKETS]
        return baskets + [(shape, obj_xy, COLOURS[colour], 6.0)]

    return OBJECT_TASKS[task], _rollout(rng, min_len, max_len, pick, place, items_of)


def episodes(name: str, seed: int, episodes_per_task: int, min_len: int, max_len: int):
    """Yield (task string, frames) for every episode of a suite, tasks in order, from `seed`."""
    if name not in SUITE_PARAMS:
        raise ValueError(f"no synthetic suite {name!r}; choose one of {sorted(SUITE_PARAMS)}")
    rng = np.random.default_rng([seed, sorted(SUITE_PARAMS).index(name)])
    for task in range(4):
        types = rng.permutation(np.arange(episodes_per_task) % 4)
        for k in range(episodes_per_task):
            if name == "spatial":
                yield spatial_episode(rng, task, min_len, max_len)
            else:
                yield object_episode(rng, task, int(types[k]), min_len, max_len)


# -- on-disk suites ---------------------------------------------------------------------------
def content_key(name: str, seed: int, **params) -> str:
    """12 hex chars identifying the generated content (generator version + all parameters)."""
    blob = json.dumps({"version": GENERATOR_VERSION, "name": name, "seed": seed,
                       "size": IMAGE_SIZE, "fps": FPS, **params}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def repo_id(name: str) -> str:
    return f"graftbench/tiny_libero_{name}"


def generate_suite(name: str, root: str | Path, seed: int, *, progress: ProgressSink,
                   **overrides) -> Path:
    """Write suite `name` as a LeRobotDataset at `root` (must not exist); returns `root`.

    `overrides` replace SUITE_PARAMS entries (episodes_per_task, min_len, max_len). `progress`:
    episodes written so far, every 30 s (a first use took 56 s on 2 busy cores, silent).
    """
    params = {**SUITE_PARAMS[name], **overrides} if name in SUITE_PARAMS else overrides
    total = 4 * params["episodes_per_task"]  # episodes() draws 4 tasks
    bar = Progress(f"suite {name}: generating", total, progress)

    def counted():
        for done, episode in enumerate(episodes(name, seed, **params)):
            bar.update(done, "episodes")  # the writer asks for the next once it wrote the last
            yield episode
        bar.update(total, "episodes")

    write_dataset(root, repo_id(name), features(), "panda", FPS, counted())
    (Path(root) / "graftbench_suite.json").write_text(json.dumps(
        {"name": name, "seed": seed, "generator_version": GENERATOR_VERSION, **params}, indent=1))
    return Path(root)


def tiny_suite_path(name: str, seed: int = 0, *, progress: ProgressSink) -> Path:
    """Folder of the cached generated suite `name`; generated (atomically) when missing,
    reporting to `progress`; another process generating it is waited for, not repeated."""
    final = _suite_folder(name, seed)
    if not _generated(final):
        with exclusive(final.with_name(final.name + ".lock")):
            if not _generated(final):
                _generate_into(final, name, seed, progress)
    return final


def prepare_tiny_suites(names: list[str], first: int, *, progress: ProgressSink) -> None:
    """Generate the missing suites of `names` that no other process is generating, beginning
    with names[first] (each xdist worker its own), so that the workers of a run generate the
    suites side by side (~15 s each on one core) instead of each waiting on every one; the
    suites left to another process are waited for when loaded (`tiny_suite_path`)."""
    order = names[first % len(names):] + names[:first % len(names)] if names else []
    for name in order:
        final = _suite_folder(name)
        if _generated(final):
            continue
        with try_exclusive(final.with_name(final.name + ".lock")) as mine:
            if mine and not _generated(final):
                _generate_into(final, name, 0, progress)


def _suite_folder(name: str, seed: int = 0) -> Path:
    params = SUITE_PARAMS.get(name)
    if params is None:
        raise ValueError(f"no synthetic suite {name!r}; choose one of {sorted(SUITE_PARAMS)}")
    return cache_dir() / "suites" / f"{name}-{content_key(name, seed, **params)}"


def _generated(final: Path) -> bool:
    return (final / "meta" / "info.json").exists()


def _generate_into(final: Path, name: str, seed: int, progress: ProgressSink) -> Path:
    return build_dataset_dir(final, lambda tmp: generate_suite(name, tmp, seed, progress=progress))
