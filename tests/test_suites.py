"""LIBERO-format suites: generation, loading, the planted visual signal, splits and windows."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from ondisk.paths import cache_dir
from bench.progress import QUIET
from bench.suites import SUITES, libero, load_suite, suite_from_dataset, synthetic
from ondisk.libero_format import IMAGE_KEYS, STATE_KEY
from bench.suites.base import Suite, SuiteUnavailable
from bench.suites.windows import (
    action_chunks,
    episode_frames,
    episode_tasks,
    eval_windows,
    heldout_split,
    raw_batch,
)

SMALL = dict(episodes_per_task=1, min_len=6, max_len=8)


@pytest.fixture(scope="module")
def spatial() -> Suite:
    return load_suite("spatial", "tiny", progress=QUIET)


@pytest.fixture(scope="module")
def objects() -> Suite:
    return load_suite("object", "tiny", progress=QUIET)


def _load(root) -> Suite:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return suite_from_dataset("spatial", LeRobotDataset("t/x", root=root), images_in_memory=True)


def _hand_suite(lengths: list[int], image_shape=(3, 4, 4)) -> Suite:
    """Episodes of the given lengths; action[f] = f in every dimension, one task per episode."""
    n = sum(lengths)
    episode = torch.repeat_interleave(torch.arange(len(lengths)), torch.tensor(lengths))
    frame = torch.cat([torch.arange(k) for k in lengths])
    return Suite(
        name="hand", repo_id="t/hand", root="", fps=10, fingerprint="0",
        camera_keys=IMAGE_KEYS, image_shape=image_shape,
        state=torch.zeros(n, 8), action=torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 7),
        episode_index=episode, frame_index=frame, task_index=episode,
        tasks=[f"task {i}" for i in range(len(lengths))], stats={},
        image_loader=lambda f: {c: torch.zeros(len(f), 3, 4, 4, dtype=torch.uint8) for c in IMAGE_KEYS},
    )


# -- generation and loading -------------------------------------------------------------------
def test_generation_is_deterministic_in_the_seed(tmp_path):
    a = _load(synthetic.generate_suite("spatial", tmp_path / "a", seed=0, progress=QUIET, **SMALL))
    b = _load(synthetic.generate_suite("spatial", tmp_path / "b", seed=0, progress=QUIET, **SMALL))
    c = _load(synthetic.generate_suite("spatial", tmp_path / "c", seed=1, progress=QUIET, **SMALL))
    assert a.fingerprint == b.fingerprint != c.fingerprint
    assert torch.equal(a.action, b.action) and torch.equal(a.state, b.state)
    frames = torch.arange(a.num_frames)
    assert all(torch.equal(a.images(frames)[k], b.images(frames)[k]) for k in IMAGE_KEYS)
    assert a.action.shape != c.action.shape or not torch.equal(a.action, c.action)


def test_tiny_suite_is_a_libero_format_lerobot_dataset(spatial):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(spatial.repo_id, root=spatial.root)
    for camera in IMAGE_KEYS:
        assert ds.features[camera]["dtype"] == "image"
        assert tuple(ds.features[camera]["shape"]) == (64, 64, 3)
        assert tuple(ds[0][camera].shape) == (3, 64, 64)
    assert tuple(ds.features[STATE_KEY]["shape"]) == (8,)
    assert tuple(ds.features["action"]["shape"]) == (7,)
    assert ds.fps == 10 and len(ds.meta.tasks) == 4
    assert ds.num_episodes == 4 * synthetic.SUITE_PARAMS["spatial"]["episodes_per_task"]
    assert ds[0]["task"] == spatial.tasks[int(ds[0]["task_index"])]
    # The Suite mirrors the dataset.
    assert spatial.state.shape == (spatial.num_frames, 8) and spatial.action.shape[1] == 7
    lengths = torch.bincount(spatial.episode_index)
    params = synthetic.SUITE_PARAMS["spatial"]
    assert lengths.min() >= params["min_len"] and lengths.max() < params["max_len"]  # all finish
    images = spatial.images(torch.tensor([0, 5, spatial.num_frames - 1]))
    for camera in IMAGE_KEYS:
        assert images[camera].shape == (3, 3, 64, 64) and images[camera].dtype == torch.float32
        assert 0.0 <= images[camera].min() and images[camera].max() <= 1.0
    assert spatial.stats["action"]["mean"].shape == (7,)


def test_tiny_suite_is_cached_under_a_content_key(spatial):
    path = synthetic.tiny_suite_path("spatial", progress=QUIET)
    assert str(path) == spatial.root and path.parent == cache_dir() / "suites"
    assert path.name == "spatial-" + synthetic.content_key("spatial", 0, **synthetic.SUITE_PARAMS["spatial"])
    assert not list(path.parent.glob(f".tmp-{path.name}-*"))
    assert load_suite("spatial", "tiny", progress=QUIET).fingerprint == spatial.fingerprint


def test_images_of_the_wrong_shape_fail_clearly():
    suite = _hand_suite([3], image_shape=(3, 8, 8))
    with pytest.raises(ValueError, match=r"\(3, 4, 4\).*\(3, 8, 8\)"):
        suite.images(torch.tensor([0]))


def test_unknown_names_and_sources_list_the_valid_ones():
    with pytest.raises(ValueError, match="valid suites: .*(object.*spatial|spatial.*object)"):
        load_suite("spatail", "tiny", progress=QUIET)
    with pytest.raises(ValueError, match="tiny.*hub"):
        load_suite("spatial", "local", progress=QUIET)
    with pytest.raises(ValueError, match="no tiny"):
        load_suite("goal", "tiny", progress=QUIET)
    assert set(SUITES) == {"spatial", "object", "goal", "10"}


# -- the planted visual signal ----------------------------------------------------------------
def _centroid(image: np.ndarray, colour: str) -> np.ndarray:
    """(col, row) centroid of pixels close to a named colour in an (H, W, 3) uint8 image."""
    ref = np.array(synthetic.COLOURS[colour])
    rows, cols = np.nonzero(np.abs(image.astype(int) - ref).max(-1) < 40)
    assert len(rows) > 0, colour
    return np.array([cols.mean(), rows.mean()])


def _first_frames(suite: Suite) -> torch.Tensor:
    return torch.nonzero(suite.frame_index == 0).flatten()


def test_spatial_action_points_at_the_target_drawn_in_the_image(spatial):
    first = _first_frames(spatial)
    images = (spatial.images(first)[IMAGE_KEYS[0]] * 255).round().byte().permute(0, 2, 3, 1).numpy()
    target, distractor = [], []
    for image, frame in zip(images, first.tolist()):
        colour = "red" if "red" in spatial.tasks[spatial.task_index[frame]] else "blue"
        other = "blue" if colour == "red" else "red"
        target.append(_centroid(image, colour))
        distractor.append(_centroid(image, other))
    action_xy = spatial.action[first, :2].numpy()
    # Frame 0 moves from wherever the eef starts towards the block drawn in the image.
    eef_xy = spatial.state[first, :2].numpy()
    towards = synthetic.pixel_to_world(np.array(target)) - eef_xy
    for axis in (0, 1):  # image col <-> world x, row <-> world y
        assert np.corrcoef(towards[:, axis], action_xy[:, axis])[0, 1] > 0.8
        assert abs(np.corrcoef(np.array(distractor)[:, axis], action_xy[:, axis])[0, 1]) < 0.5
    # The state alone does not decide the action (the eef starts anywhere); with the target
    # read from the image it does.
    assert _r2(eef_xy, action_xy) < 0.6
    assert _r2(np.c_[eef_xy, target], action_xy) > 0.8


def _slot_of(colrow: np.ndarray, z: float) -> np.ndarray:
    """World xyz of the spatial slot nearest a drawn centroid (col, row), at height z."""
    xy = synthetic.pixel_to_world(colrow)
    slot = synthetic.SPATIAL_SLOTS[np.argmin(np.linalg.norm(synthetic.SPATIAL_SLOTS - xy, axis=1))]
    assert np.linalg.norm(slot - xy) < 0.01, "object not drawn at a slot"
    return np.r_[slot, z]


def test_grasp_and_release_happen_where_the_image_shows_the_goal(spatial):
    """The expert is event-driven: the gripper closes on reaching the block drawn in frame 0 and
    opens on reaching the destination, at frame indices that vary (no hidden clock)."""
    first = _first_frames(spatial)
    images = (spatial.images(first)[IMAGE_KEYS[0]] * 255).round().byte().permute(0, 2, 3, 1).numpy()
    eef = spatial.state[:, :3].numpy()  # the eef before each frame's action, 2 mm noise
    noise = 0.006
    grasp_frames = []
    for image, f0 in zip(images, first.tolist()):
        task = spatial.tasks[spatial.task_index[f0]]
        frames = torch.nonzero(spatial.episode_index == spatial.episode_index[f0]).flatten()
        closing = frames[spatial.action[frames, 6] > 0]
        grasp, release = int(closing[0]), int(closing[-1]) + 1
        assert torch.equal(closing, torch.arange(grasp, release)), "one grasp, one release"
        block = _slot_of(_centroid(image, "red" if "red" in task else "blue"), 0.03)
        dest = _slot_of(_centroid(image, "plate" if "plate" in task else "bowl"), 0.08)
        assert np.linalg.norm(eef[grasp] - block) < synthetic.REACH_TOL + noise
        assert np.linalg.norm(eef[grasp - 1] - block) > synthetic.REACH_TOL - noise
        assert np.linalg.norm(eef[release] - dest) < synthetic.REACH_TOL + noise
        assert np.linalg.norm(eef[release - 1] - dest) > synthetic.REACH_TOL - noise
        grasp_frames.append(grasp - f0)
    assert len(set(grasp_frames)) >= 4


def _r2(x: np.ndarray, y: np.ndarray) -> float:
    """R^2 of the least-squares linear fit y ~ [x, 1] (all output columns pooled)."""
    design = np.c_[x, np.ones(len(x))]
    fit = design @ np.linalg.lstsq(design, y, rcond=None)[0]
    return 1.0 - ((y - fit) ** 2).sum() / ((y - y.mean(0)) ** 2).sum()


def test_object_identity_in_the_image_decides_the_destination(objects):
    first = _first_frames(objects)
    images = (objects.images(first)[IMAGE_KEYS[0]] * 255).round().byte().permute(0, 2, 3, 1).numpy()
    colours = [name.split()[0] for name in synthetic.OBJECT_TYPES]
    last = torch.nonzero(torch.diff(objects.episode_index, append=torch.tensor([-1])) != 0).flatten()
    destinations_per_task: dict[int, set] = {}
    for image, f0, f1 in zip(images, first.tolist(), last.tolist()):
        counts = [(np.abs(image.astype(int) - synthetic.COLOURS[c]).max(-1) < 40).sum() for c in colours]
        identity = int(np.argmax(counts))
        final_xy = objects.state[f1, :2].numpy()
        basket = int(np.argmin(np.linalg.norm(synthetic.BASKETS - final_xy, axis=1)))
        task = int(objects.task_index[f0])
        assert basket == synthetic.object_destination(identity, task)
        destinations_per_task.setdefault(task, set()).add(basket)
    # The task string alone does not decide where the object goes.
    assert all(len(d) >= 3 for d in destinations_per_task.values())


# -- held-out split, windows, chunks ----------------------------------------------------------
def test_heldout_split_is_whole_episodes_per_task_from_the_split_seed_only(spatial):
    train, heldout = heldout_split(spatial, split_seed=1234, per_task=2)
    assert sorted(train + heldout) == spatial.episodes and not set(train) & set(heldout)
    tasks = episode_tasks(spatial)
    assert sorted(tasks[e] for e in heldout) == [0, 0, 1, 1, 2, 2, 3, 3]
    train_frames, heldout_frames = episode_frames(spatial, train), episode_frames(spatial, heldout)
    assert len(train_frames) + len(heldout_frames) == spatial.num_frames
    assert not set(spatial.episode_index[train_frames].tolist()) & set(heldout)
    torch.manual_seed(99)
    np.random.seed(99)  # a cell seed must not move the split
    assert heldout_split(spatial, 1234, 2) == (train, heldout)
    assert heldout_split(spatial, 1235, 2)[1] != heldout
    per_task = synthetic.SUITE_PARAMS["spatial"]["episodes_per_task"]
    with pytest.raises(ValueError, match=f"{per_task} episodes"):
        heldout_split(spatial, 1234, per_task=per_task)


def test_eval_windows_every_stride_frames_from_frame_zero():
    suite = _hand_suite([5, 7])
    assert eval_windows(suite, [0, 1], stride=3).tolist() == [0, 3, 5, 8, 11]
    assert eval_windows(suite, [1], stride=10).tolist() == [5]


def test_action_chunks_repeat_the_last_action_and_mark_padding():
    suite = _hand_suite([3, 4])  # frames 0-2 | 3-6, action[f] = f
    actions, is_pad = action_chunks(suite, torch.tensor([1, 3, 6]), chunk=4)
    assert actions[:, :, 0].tolist() == [[1, 2, 2, 2], [3, 4, 5, 6], [6, 6, 6, 6]]
    assert is_pad.tolist() == [[False, False, True, True], [False] * 4, [False, True, True, True]]
    assert actions.shape == (3, 4, 7) and actions.dtype == torch.float32


def test_raw_batch_has_the_documented_keys(spatial):
    frames = eval_windows(spatial, heldout_split(spatial, 1234, 2)[1], stride=6)[:4]
    batch = raw_batch(spatial, frames, chunk=50)
    assert set(batch) == {*IMAGE_KEYS, STATE_KEY, "action", "action_is_pad", "task"}
    assert batch[IMAGE_KEYS[1]].shape == (4, 3, 64, 64) and batch[STATE_KEY].shape == (4, 8)
    assert batch["action"].shape == (4, 50, 7) and batch["action_is_pad"].shape == (4, 50)
    assert batch["action_is_pad"][:, -1].all()  # episodes are shorter than 50 frames
    assert batch["task"] == [spatial.tasks[t] for t in spatial.task_index[frames]]
    assert set(raw_batch(spatial, frames, 50, with_images=False)) == {STATE_KEY, "action",
                                                                       "action_is_pad", "task"}


# -- the real source --------------------------------------------------------------------------
def test_hub_suite_absent_offline_fails_fast_naming_repo_and_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.delenv(libero.ROOT_ENV, raising=False)
    monkeypatch.setattr(libero, "lerobot_home", lambda: tmp_path / "lerobot")
    start = time.perf_counter()
    with pytest.raises(SuiteUnavailable) as err:
        load_suite("spatial", "hub", progress=QUIET)
    assert time.perf_counter() - start < 2.0
    assert "lerobot/libero_spatial_image" in str(err.value) and str(tmp_path / "lerobot") in str(err.value)
    assert "\n" not in str(err.value)


def test_hub_source_loads_a_local_libero_copy(spatial):
    suite = load_suite("spatial", "hub", root=spatial.root, progress=QUIET)
    assert torch.equal(suite.action, spatial.action) and suite.tasks == spatial.tasks
    frames = torch.tensor([0, 17])
    assert torch.allclose(suite.images(frames)[IMAGE_KEYS[0]], spatial.images(frames)[IMAGE_KEYS[0]])


def test_hub_dataset_missing_a_feature_names_it(tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = synthetic.features()
    del features[IMAGE_KEYS[1]]
    ds = LeRobotDataset.create("lerobot/libero_spatial_image", fps=10, features=features,
                               root=tmp_path / "libero_spatial_image", use_videos=False)
    for _ in range(2):
        ds.add_frame({IMAGE_KEYS[0]: np.zeros((64, 64, 3), np.uint8),
                      STATE_KEY: np.zeros(8, np.float32), "action": np.zeros(7, np.float32),
                      "task": "t"})
    ds.save_episode()
    ds.finalize()
    with pytest.raises(SuiteUnavailable, match="missing camera feature 'observation.images.wrist_image'"):
        load_suite("spatial", "hub", root=tmp_path, progress=QUIET)


def test_validate_features_names_a_wrong_shape():
    features = synthetic.features()
    features[STATE_KEY] = {"dtype": "float32", "shape": (7,)}
    with pytest.raises(SuiteUnavailable, match=r"'observation.state' has shape \(7,\), expected \(8,\)"):
        libero.validate_features(features, "t/x")


def test_an_unselected_suite_the_tiny_release_needs_says_why_it_loads(tmp_path, monkeypatch):
    """--suites spatial still loads (on a fresh clone: generates) the object suite: the tiny
    release trains on both, so the numbers do not depend on the selection. It used to load
    without a word of why."""
    import bench.resources.workspace as workspace
    from bench.grid.protocol import TINY, with_overrides
    from bench.results.store import ResultStore

    class Lines:
        def __init__(self):
            self.lines = []

        def line(self, text):
            self.lines.append(text)

    monkeypatch.delenv("GRAFTBENCH_QUIET", raising=False)
    stub = Suite.__new__(Suite)
    stub.state, stub.episode_index = torch.zeros(3, 8), torch.zeros(3, dtype=torch.long)
    monkeypatch.setattr(workspace, "load_suite", lambda *a, **k: stub)
    sink = Lines()
    ws = workspace.Workspace(with_overrides(TINY, suites=("spatial",)), ResultStore(tmp_path),
                             progress=sink)
    ws.suite("object")
    ws.suite("spatial")
    assert sink.lines[0] == ("[graftbench] suite object (tiny): loading (generated on first use, "
                             "then cached; not selected, but the tiny release trains on both tiny "
                             "suites, so its numbers do not depend on the selection)")
    assert sink.lines[2] == ("[graftbench] suite spatial (tiny): loading (generated on first "
                             "use, then cached)")


def test_every_table_refuses_an_unknown_name_in_one_shape():
    """Suites, perturbations, cell kinds (bench.table), backbones and encoders (below bench):
    "unknown <what> 'x' (did you mean 'y'?); valid <plural>: ..."."""
    from backbones import get_entry
    from bench.grid.kinds import CELL_KINDS
    from bench.robust.perturbations import PERTURBATIONS
    from encoders.registry import get_spec

    refusals = [SUITES.refusal("spatail"), PERTURBATIONS.refusal("blurr"),
                CELL_KINDS.refusal("graf")]
    for call, name in ((get_entry, "smolvlm"), (get_spec, "pixel")):
        with pytest.raises(ValueError) as err:
            call(name)
        refusals.append(str(err.value))
    for line, what, close in zip(refusals, ("suite", "perturbation kind", "cell kind",
                                            "backbone", "encoder"),
                                 ("spatial", "blur", "graft", "smolvla", "pixels")):
        assert line.startswith(f"unknown {what} "), line
        assert f"(did you mean {close!r}" in line and "; valid " in line, line
    # a name in another case is offered the name itself, not a neighbour ('smolvla_L' was
    # offered 'smolvla', the family's smallest size, not its largest)
    offered = [SUITES.refusal("Spatial")]
    for call, name in ((get_entry, "smolvla_L"), (get_spec, "DINOv2_S")):
        with pytest.raises(ValueError) as err:
            call(name)
        offered.append(str(err.value))
    for line, close in zip(offered, ("spatial", "smolvla_l", "dinov2_s")):
        assert f"(did you mean {close!r}" in line, line


def _fake_generation(made: list[str]):
    def generate(final, name, seed, progress):
        made.append(name)
        (final / "meta").mkdir(parents=True)
        (final / "meta" / "info.json").write_text("{}")
        return final
    return generate


def test_two_workers_generate_the_tiny_suites_side_by_side(tmp_path, monkeypatch):
    """Worker k begins with the k-th suite; a suite another process is generating is left to it
    (its lock held), and loading it then waits for it instead of generating it twice."""
    from ondisk.filelock import exclusive

    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path))
    made: list[str] = []
    monkeypatch.setattr(synthetic, "_generate_into", _fake_generation(made))
    names = sorted(synthetic.SUITE_PARAMS)
    assert len(names) == 2
    synthetic.prepare_tiny_suites(names, 1, progress=QUIET)
    assert made == [names[1], names[0]]
    synthetic.prepare_tiny_suites(names, 0, progress=QUIET)  # all there: nothing again
    assert made == [names[1], names[0]]

    made.clear()
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "second"))
    other = synthetic._suite_folder(names[0])
    with exclusive(other.with_name(other.name + ".lock")):  # the other worker's, generating
        synthetic.prepare_tiny_suites(names, 0, progress=QUIET)
        assert made == [names[1]]
    assert synthetic.tiny_suite_path(names[0], progress=QUIET) == other
    assert made == [names[1], names[0]]  # the lock came free with nothing there: made once
