"""Batched rollouts (bench.sim.batched) give the B = 1 episodes: same init states, seeds, rows.

The fast test drives the real batched loop through gymnasium's real SyncVectorEnv over a toy
env whose outcome depends on the init state, the env seed and every action it is handed, so a
slot that got another episode's init state, seed or actions changes a row.
"""

from __future__ import annotations

import numpy as np
from bench.progress import QUIET
import pytest
import torch

from bench.sim import env as sim_env
from bench.sim.batching import Batching
from bench.sim.rollout import RolloutSpec, Scenes, run_rollouts
from tests.sim_marks import needs_libero

gym = pytest.importorskip("gymnasium")
TASKS = ["reach the far mark", "reach the near mark"]


class Toy(gym.Env):
    """1-D reach: success when position >= 1. Speed comes from the policy; the env seed makes
    one episode in three slip (half speed); init state 47 of task 1 never moves."""

    observation_space = gym.spaces.Dict({"p": gym.spaces.Box(-9, 9, (1,)),
                                         "gain": gym.spaces.Box(0, 9, (1,))})
    action_space = gym.spaces.Box(-1, 1, (7,))

    def __init__(self, task: int):
        self.task, self.p, self.gain, self.slip = task, 0.0, 0.0, False

    def reset(self, *, seed=None, options=None):
        init = (options or {}).get("init_state", 49)
        self.p, self.slip = 0.0, seed is not None and seed % 3 == 0
        stuck = (self.task, init) == (1, 47)
        self.gain = 0.0 if stuck else 0.1 * (1 + (init + self.task) % 4)
        return self._obs(), {"is_success": False}

    def step(self, action):
        self.p += float(action[0]) * (0.5 if self.slip else 1.0)
        return self._obs(), 0.0, self.p >= 1.0, False, {"is_success": self.p >= 1.0}

    def _obs(self):
        return {"p": np.array([self.p], np.float32), "gain": np.array([self.gain], np.float32)}


def toy_reset_to(env, init_state, seed):
    return env.reset(seed=seed, options={"init_state": init_state})[0]


def toy_observe(batched, texts):
    return {"observation.state": torch.as_tensor(np.concatenate(
        [batched["p"], batched["gain"]], axis=1)), "task": list(texts)}


class Policy:
    """Deterministic per row: a chunk of 3 actions at the row's own gain, slowing down near 1."""

    def __init__(self):
        self.calls = []

    def __call__(self, raw):
        state = raw["observation.state"]
        self.calls.append(len(state))
        speed = state[:, 1] * (1.0 + (state[:, 0] < 0.5).float())
        chunk = torch.zeros(len(state), 3, 7)
        chunk[:, :, 0] = speed[:, None]
        return chunk


def toy_scenes():
    from bench.sim.batched import VectorScenes, make_paired

    single = Scenes(lambda suite, task, render, max_steps=None: Toy(task), lambda s: TASKS,
                    lambda env: 50, toy_reset_to,
                    lambda obs, texts: toy_observe({k: np.stack([o[k] for o in obs]) for k in
                                                    obs[0]}, texts))
    built = []

    def make_vector_env(suite, task, render, max_steps, batch, mode):
        built.append(batch)
        slots = [lambda i=i: make_paired(Toy(task), i, toy_reset_to) for i in range(batch)]
        return gym.vector.SyncVectorEnv(slots, autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP)

    return single, VectorScenes(make_vector_env, lambda s: TASKS, 50, toy_observe), built


def outcomes(result):
    return [(e["task"], e["episode"], e["init_state"], e["success"], e["steps"])
            for e in result["episodes"]]


def test_batched_rollouts_give_the_single_env_episodes_with_fewer_policy_calls():
    spec = RolloutSpec("spatial", tasks=(0, 1), episodes_per_task=5, seed=0, max_steps=12,
                       n_action_steps=2)
    single, vector, built = toy_scenes()
    one, many = Policy(), Policy()
    base = run_rollouts(one, spec, progress=QUIET, scenes=single)
    batched = run_rollouts(many, spec, progress=QUIET, scenes=single, batching=Batching(3),
                           vector_scenes=vector)
    assert outcomes(batched) == outcomes(base)
    # Not a trivial answer: episodes of both kinds and several lengths, slips included.
    assert {e[3] for e in outcomes(base)} == {True, False}
    assert len({e[4] for e in outcomes(base)}) >= 3
    assert built == [3, 3] and max(many.calls) == 3 and set(one.calls) == {1}
    # The same chunks are asked for (rows), in fewer calls: slots drift out of phase, so a
    # call covers the slots whose chunk ran out at that step.
    assert sum(many.calls) == sum(one.calls) and len(many.calls) < 0.7 * len(one.calls)
    assert batched["settings"]["batch"] == 3 and base["settings"]["batch"] == 1

    # Resumed per episode as at B = 1: finished rows kept, only the others rolled out.
    rerun = Policy()
    resumed = run_rollouts(rerun, spec, progress=QUIET, scenes=single, batching=Batching(3),
                           vector_scenes=vector, finished=base["episodes"][:8])
    assert outcomes(resumed) == outcomes(base) and built[2:] == [2]  # 2 left: 2 slots
    assert resumed["settings"]["resumed_episodes"] == 8


def test_a_privileged_policy_is_refused_in_a_batch():
    from bench.sim.expert import ExpertPolicy

    spec = RolloutSpec("spatial", tasks=(0,), episodes_per_task=2, seed=0, max_steps=5,
                       n_action_steps=1)
    single, vector, _ = toy_scenes()
    with pytest.raises(ValueError, match="batch 1"):
        run_rollouts(ExpertPolicy("spatial"), spec, progress=QUIET, scenes=single, batching=Batching(2),
                     vector_scenes=vector)


@pytest.mark.slow  # LIBERO scenes rendered in the simulator
@needs_libero
def test_libero_vector_env_meets_the_single_env_observations():
    """LeRobot's vector env (sync) of 2 slots, 3 short episodes: the policy sees exactly the
    observations it sees at B = 1 (init states, seeds, render settings and actions routed to
    the right slot), and the rows are equal."""
    spec = RolloutSpec("spatial", tasks=(0,), episodes_per_task=3, seed=0, max_steps=6,
                       n_action_steps=3)
    render = sim_env.RenderSettings(image_size=32)

    def recorder(seen):
        def act(raw):
            state = raw["observation.state"]
            seen.extend(s.numpy().tobytes() + i.numpy().tobytes() for s, i in
                        zip(state, raw["observation.images.image"]))
            chunk = torch.zeros(len(state), 3, 7)  # a state-dependent push
            chunk[:, :, 0] = torch.sign(state[:, 1:2]) * 0.5
            chunk[:, :, 6] = -1.0
            return chunk
        return act

    alone, together = [], []
    base = run_rollouts(recorder(alone), spec, progress=QUIET, render=render)
    batched = run_rollouts(recorder(together), spec, progress=QUIET, render=render, batching=Batching(2))
    assert outcomes(batched) == outcomes(base)
    assert sorted(together) == sorted(alone) and len(alone) == 3 * 2


def test_a_policy_that_raises_in_a_batch_fails_the_cell_naming_the_episodes():
    from bench.sim.rollout import RolloutCrashed

    spec = RolloutSpec("spatial", tasks=(0,), episodes_per_task=3, seed=0, max_steps=12,
                       n_action_steps=2)
    single, vector, _ = toy_scenes()

    def broken(raw):
        raise RuntimeError("CUDA out of memory")

    with pytest.raises(RolloutCrashed, match=r"spatial task 0 episode 0 \(init state 49\), "
                       r"episode 1 \(init state 48\): the policy: RuntimeError: CUDA out of"):
        run_rollouts(broken, spec, progress=QUIET, scenes=single, batching=Batching(2), vector_scenes=vector)
