"""Closed-loop rollouts: known answers through the rollout path (expert, zero actions), pairing,
and the worker pool a process keeps across runs (on a toy scene: ~1 min on 2 shared cores, six
spawned workers)."""

from __future__ import annotations

import os
import signal
from dataclasses import replace

import numpy as np
from bench.progress import QUIET
import pytest
import torch

from bench.sim import env as sim_env
from bench.sim.batching import Batching
from bench.sim.rollout import (RolloutCrashed, RolloutSpec, Scenes, rollout_env_seed,
                               rollout_init_state, run_rollouts)
from bench.stats import wilson_interval
from tests.sim_marks import needs_libero


def test_wilson_interval_known_answers():
    lo, hi = wilson_interval(0, 1)
    assert lo == 0.0 and hi == pytest.approx(1.96**2 / (1 + 1.96**2), abs=1e-3)
    lo, hi = wilson_interval(5, 10)
    assert lo == pytest.approx(0.2366, abs=1e-3) and hi == pytest.approx(0.7634, abs=1e-3)
    assert wilson_interval(0, 0) == (0.0, 1.0)  # no episode: every rate is consistent


def test_init_states_and_seeds_depend_on_the_spec_only():
    assert [rollout_init_state(e, 50) for e in range(3)] == [49, 48, 47]
    assert rollout_env_seed(0, 1, 2) == rollout_env_seed(0, 1, 2) != rollout_env_seed(1, 1, 2)
    with pytest.raises(ValueError, match="suite"):
        RolloutSpec("goal", (0,), 1, 0, 10, 1)


def test_demo_specs_refuse_a_task_the_expert_cannot_solve():
    from bench.sim.demos import DEFAULT_SPECS, DemoSpec, demo_spec

    more = demo_spec("spatial", (0, 1), 20)
    assert (more.tasks, more.episodes_per_task, more.max_attempts) == ((0, 1), 20, 24)
    assert more.key() != DEFAULT_SPECS["spatial"].key() and demo_spec("object") == \
        DEFAULT_SPECS["object"]
    noisy = demo_spec("spatial", (0, 1), 20, action_noise=0.3)  # DART: another dataset
    assert noisy.action_noise == 0.3 and noisy.key() != more.key()
    assert replace(noisy, action_noise=0.0).key() == more.key()  # no noise: the old key
    slow = demo_spec("spatial", (0, 1), 20, expert_speed=0.5)  # an unsaturated expert
    assert slow.key() != more.key() and replace(slow, expert_speed=1.0).key() == more.key()
    # Pinned: the key of the cached suite of studies/sim/README.md's attempts 1-2, made before the
    # noise and speed fields existed (a default field in the key would rename every cached suite).
    assert demo_spec("spatial", (0, 1), 10).key() == "fe3b20524c9d"
    with pytest.raises(ValueError, match="give 0 < speed <= 1"):
        demo_spec("spatial", (0, 1), expert_speed=0.0)
    with pytest.raises(ValueError, match=r"cannot solve LIBERO-object task 6 \(measured 0/5"):
        DemoSpec("object", tasks=(0, 6))
    with pytest.raises(ValueError, match="task 10 is not a LIBERO-spatial task id"):
        demo_spec("spatial", (10,))


def test_a_slowed_expert_keeps_its_moves_within_the_cap_and_on_course():
    """ExpertParams.speed < 1: translation within +-speed, pointing at the waypoint (direction
    kept, unlike a per-axis clip); inside the cap it is the same P-controller; 1 is the original
    per-axis clip at +-1."""
    from bench.sim.expert import ExpertParams, ScriptedExpert

    far, near = np.array([0.30, -0.10, 0.02]), np.array([0.02, -0.01, 0.0])
    original = ScriptedExpert("spatial")._translation(far)
    np.testing.assert_array_equal(original, [1.0, -1.0, 0.24])  # 12 per metre, clipped per axis
    slow = ScriptedExpert("spatial", ExpertParams(speed=0.5))
    action = slow._translation(far)
    assert np.abs(action).max() == pytest.approx(0.5)
    np.testing.assert_allclose(action / np.linalg.norm(action), far / np.linalg.norm(far))
    np.testing.assert_allclose(slow._translation(near), 12.0 * near)  # unsaturated


def test_a_sim_spec_picks_its_own_cached_suite(monkeypatch):
    """load_suite(..., sim_spec=) (the workspace's --sim-tasks / --sim-demos) looks for the
    dataset of that spec, not the default one."""
    from bench.sim.demos import demo_spec
    from bench.suites import SuiteUnavailable, load_suite

    monkeypatch.setattr(sim_env, "libero_available", lambda: False)
    spec = demo_spec("spatial", (2, 3), 7)  # never generated: the message names its folder
    with pytest.raises(SuiteUnavailable, match=f"spatial-{spec.key()}"):
        load_suite("spatial", "sim", sim_spec=spec, progress=QUIET)


def test_sim_suite_without_the_extra_fails_in_one_line(monkeypatch, tmp_path):
    from bench.suites import SuiteUnavailable, load_suite

    monkeypatch.setattr(sim_env, "libero_available", lambda: False)
    with pytest.raises(SuiteUnavailable, match="install_libero.sh"):
        load_suite("spatial", "sim", root=tmp_path / "absent", progress=QUIET)


SMALL = sim_env.RenderSettings(image_size=64)


@pytest.mark.slow  # LIBERO scenes rendered in the simulator
@needs_libero
def test_scripted_expert_as_policy_succeeds():
    from bench.sim.expert import ExpertPolicy
    from bench.sim.rollout import run_rollouts

    spec = RolloutSpec("spatial", tasks=(0,), episodes_per_task=1, seed=0, max_steps=200,
                       n_action_steps=1)
    result = run_rollouts(ExpertPolicy("spatial"), spec, progress=QUIET, render=SMALL)
    assert result["success_rate"] == 1.0
    (episode,) = result["episodes"]
    assert episode["success"] and episode["init_state"] == 49 and episode["steps"] < 200
    assert result["per_task"]["0"]["successes"] == 1
    assert result["settings"]["render"]["image_size"] == 64


@pytest.mark.slow  # LIBERO scenes rendered in the simulator
@needs_libero
def test_zero_action_policy_never_succeeds_and_sees_dataset_conventions():
    from bench.sim.rollout import run_rollouts

    seen = []

    def zero_act(raw: dict) -> torch.Tensor:
        seen.append(raw)
        return torch.zeros(len(raw["task"]), 10, 7)

    spec = RolloutSpec("spatial", tasks=(0,), episodes_per_task=1, seed=0, max_steps=40,
                       n_action_steps=10)
    result = run_rollouts(zero_act, spec, progress=QUIET, render=SMALL)
    assert result["success_rate"] == 0.0 and result["episodes"][0]["steps"] == 40
    assert len(seen) == 4  # 40 steps / 10 executed per chunk
    raw = seen[0]
    assert raw["observation.images.image"].shape == (1, 3, 64, 64)
    assert raw["observation.images.wrist_image"].dtype == torch.float32
    assert 0.0 <= float(raw["observation.images.image"].min()) <= 1.0
    assert raw["observation.state"].shape == (1, 8)
    assert raw["task"] == [sim_env.task_descriptions("spatial")[0]]
    assert np.isfinite(raw["observation.state"].numpy()).all()


class Reach:
    """1-D reach, no simulator: success at position >= 1, the gain set by the init state and
    env seed, so an episode run on another init state, seed or step cap changes its row."""

    def __init__(self, task: int):
        self.task, self.p, self.gain = task, 0.0, 0.0

    def reset(self, init_state: int, seed: int) -> np.ndarray:
        self.p, self.gain = 0.0, 0.05 * (1 + (init_state + seed + self.task) % 5)
        return self._obs()

    def step(self, action):
        self.p += float(action[0]) * self.gain
        return self._obs(), 0.0, False, False, {"is_success": self.p >= 1.0}

    def _obs(self) -> np.ndarray:
        return np.array([self.p, self.gain], np.float32)

    def close(self) -> None:
        pass


def reach_env(suite, task, render, max_steps=None):
    if task == 3:  # a worker that errors
        raise RuntimeError("no scene for task 3")
    return Reach(task)


def reach_observe(obs, texts):
    return {"observation.state": torch.from_numpy(np.stack(obs)), "task": list(texts)}


def reach_descriptions(suite):
    return ["reach", "reach further", "reach back", "reach nowhere"]


def reach_init_states(env):
    return 50


def reach_reset_to(env, init_state, seed):
    return env.reset(init_state, seed)


# Functions by name, not lambdas: spawned workers unpickle the scenes.
REACH = Scenes(reach_env, reach_descriptions, reach_init_states, reach_reset_to, reach_observe)


def reach_act(raw):
    chunk = torch.ones(1, 4, 7)
    chunk[:, :, 0] += (raw["observation.state"][:, :1] < 0.5).float()  # faster while far
    return chunk


def outcomes(result: dict) -> list[tuple]:
    return [(e["task"], e["episode"], e["init_state"], e["success"], e["steps"])
            for e in result["episodes"]]


def pids(pool) -> list[int]:
    return [slot.process.pid for slot in pool.slots]


@pytest.mark.slow  # spawns worker processes: fresh interpreters
def test_a_kept_pool_serves_its_own_key_only_and_a_broken_one_is_replaced():
    from bench.sim import workers

    spec = RolloutSpec("spatial", tasks=(0, 1), episodes_per_task=3, seed=0, max_steps=12,
                       n_action_steps=3)
    shorter = replace(spec, max_steps=7)
    alone = [outcomes(run_rollouts(reach_act, s, QUIET, scenes=REACH)) for s in (spec, shorter)]
    assert alone[0] != alone[1]  # the step cap changes rows: a pool must not mix them up
    two = Batching(workers=2)
    try:
        workers.discard_workers()
        assert outcomes(run_rollouts(reach_act, spec, QUIET, scenes=REACH, batching=two)) == \
            alone[0]
        first = workers.kept_pool()
        assert outcomes(run_rollouts(reach_act, spec, QUIET, scenes=REACH, batching=two)) == \
            alone[0]
        assert workers.kept_pool() is first and len(set(pids(first))) == 2  # the same workers
        # another step cap: another key; the old pool is stopped before the new one starts
        assert outcomes(run_rollouts(reach_act, shorter, QUIET, scenes=REACH, batching=two)) == \
            alone[1]
        second = workers.kept_pool()
        assert not set(pids(second)) & set(pids(first))
        assert not any(slot.process.is_alive() for slot in first.slots)
        # a worker that died between runs: a fresh pool, the same rows
        os.kill(second.slots[0].process.pid, signal.SIGKILL)
        second.slots[0].process.join(30)
        assert outcomes(run_rollouts(reach_act, shorter, QUIET, scenes=REACH, batching=two)) == \
            alone[1]
        third = workers.kept_pool()
        assert not set(pids(third)) & set(pids(second))
        assert not any(slot.process.is_alive() for slot in second.slots)
        # a worker that errors (task 3's env cannot be built): its pool is not kept
        with pytest.raises(RolloutCrashed, match="no scene for task 3"):
            run_rollouts(reach_act, replace(shorter, tasks=(0, 3)), QUIET, scenes=REACH,
                         batching=two)
        assert workers.kept_pool() is None
        assert not any(slot.process.is_alive() for slot in third.slots)
    finally:
        workers.discard_workers()
