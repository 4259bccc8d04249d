"""Scripted LIBERO demonstrations: dataset format, conventions vs LiberoEnv, replay, determinism."""

from __future__ import annotations

import json

import numpy as np
from bench.progress import QUIET
import pytest
import torch

from bench.sim import env as sim_env

if not sim_env.libero_available():
    pytest.skip("libero extra not installed (bash scripts/install_libero.sh)", allow_module_level=True)

from bench.sim import demos  # noqa: E402
from bench.suites import libero, suite_from_dataset  # noqa: E402
from ondisk.libero_format import ACTION_KEY, IMAGE_KEYS, STATE_KEY  # noqa: E402

pytestmark = pytest.mark.slow  # demonstrations generated in the LIBERO simulator

# One task where the expert is known to succeed (LIBERO-Spatial task 0: 10/10 measured), small
# images so the test stays around a minute on 2 cores.
SPEC = demos.DemoSpec("spatial", tasks=(0,), episodes_per_task=1, max_attempts=2, seed=0,
                      image_size=64)


@pytest.fixture(scope="module")
def demo_root():
    """The spec's suite where a run keeps it (the cache, keyed on the generator's version and
    the spec): generated on a cold cache, reused warm (~15 s). The generator itself runs in
    test_generation_is_deterministic, which builds it afresh and compares the two."""
    return demos.generate(SPEC, None, progress=QUIET)


@pytest.fixture(scope="module")
def dataset(demo_root):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(demos.repo_id("spatial"), root=demo_root)


def _columns(ds, keys):
    return ds.hf_dataset.with_format("numpy", columns=keys)[:]


def test_dataset_has_libero_names_shapes_and_expert_record(dataset, demo_root):
    libero.validate_features(dataset.features, dataset.repo_id)
    for camera in IMAGE_KEYS:
        assert dataset.features[camera]["dtype"] == "image"
        assert tuple(dataset.features[camera]["shape"]) == (64, 64, 3)
    assert tuple(dataset.features[STATE_KEY]["shape"]) == (8,)
    assert tuple(dataset.features[ACTION_KEY]["shape"]) == (7,)
    assert dataset.fps == sim_env.CONTROL_HZ
    suite = suite_from_dataset("spatial", dataset, images_in_memory=True)
    assert suite.tasks == [sim_env.task_descriptions("spatial")[0]]
    assert suite.image_shape == (3, 64, 64)
    actions = suite.action.numpy()
    assert np.all(np.abs(actions) <= 1.0) and set(np.unique(actions[:, 6])) <= {-1.0, 1.0}
    record = json.loads((demo_root / demos.EXPERT_SUCCESS_FILE).read_text())
    assert record["0"]["successes"] == 1 and record["0"]["success_rate"] > 0


def test_first_frame_matches_liberoenv_conventions(dataset, demo_root):
    """Frame 0 of an episode == LiberoEnv's observation of the same init state, turned 180
    degrees (LeRobot's LIBERO processor), state = eef pos + axis-angle + gripper qpos."""
    episode = json.loads((demo_root / demos.SUITE_FILE).read_text())["episodes"][0]
    env = sim_env.make_env("spatial", 0, sim_env.RenderSettings(image_size=64))
    try:
        obs = sim_env.reset_to(env, episode["init_state"],
                               demos.episode_seed(SPEC.seed, 0, episode["init_state"]))
    finally:
        env.close()
    row = _columns(dataset, [*IMAGE_KEYS, STATE_KEY])
    for camera, libero_name in zip(IMAGE_KEYS, ("image", "wrist_image")):
        stored = row[camera][0]
        assert stored.shape == (64, 64, 3)
        np.testing.assert_array_equal(stored, obs["pixels"][libero_name][::-1, ::-1])
    state = row[STATE_KEY][0]
    robot = obs["robot_state"]
    np.testing.assert_allclose(state[:3], robot["eef"]["pos"], atol=1e-6)
    np.testing.assert_allclose(state[6:8], robot["gripper"]["qpos"], atol=1e-6)
    x, y, z, w = robot["eef"]["quat"]  # (x, y, z, w) -> axis-angle, as robosuite defines it
    angle = 2.0 * np.arccos(np.clip(w, -1.0, 1.0))
    np.testing.assert_allclose(state[3:6], np.array([x, y, z]) / np.sqrt(1.0 - w * w) * angle,
                               atol=1e-4)


def test_replaying_recorded_actions_reproduces_success(dataset, demo_root):
    from bench.sim.rollout import replay

    episode = json.loads((demo_root / demos.SUITE_FILE).read_text())["episodes"][0]
    actions = _columns(dataset, [ACTION_KEY])[ACTION_KEY]
    result = replay(actions, "spatial", 0, episode["init_state"],
                    demos.episode_seed(SPEC.seed, 0, episode["init_state"]),
                    sim_env.RenderSettings(image_size=64))
    assert result["success"] and result["steps"] == len(actions)


def test_generation_is_deterministic(dataset, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    again = LeRobotDataset(demos.repo_id("spatial"),
                           root=demos.generate(SPEC, tmp_path / "again", progress=QUIET))
    keys = [*IMAGE_KEYS, STATE_KEY, ACTION_KEY, "episode_index", "frame_index"]
    first, second = _columns(dataset, keys), _columns(again, keys)
    for key in keys:
        np.testing.assert_array_equal(first[key], second[key], err_msg=key)


def test_load_suite_sim_source_reads_the_generated_dataset(demo_root, dataset):
    from bench.suites import load_suite

    suite = load_suite("spatial", "sim", root=demo_root, progress=QUIET)
    assert suite.repo_id == demos.repo_id("spatial") and suite.fps == sim_env.CONTROL_HZ
    assert suite.num_frames == dataset.num_frames and suite.state.shape[1] == 8
    images = suite.images(torch.arange(2))
    assert images[IMAGE_KEYS[0]].shape == (2, 3, 64, 64)
    assert demos.libero_task_ids(suite.root) == [0]
    assert demos.render_settings(suite.root) == sim_env.RenderSettings(image_size=64)
