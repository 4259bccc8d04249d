"""Rollouts that render only the frames they read, over worker processes, give the rows and the
observations of the loop that renders every step in this process (bench.sim.frames,
bench.sim.workers), and so does a second run on the workers the first one left (the next cell
of a process): same init states, env seeds, frames, actions and per-episode rows, with the
substeps' repeated MuJoCo forward skipped (bench.sim.physics).

The policy pushes the arm by what it sees (state and pixels), so a frame rendered at the wrong
step, a placeholder read, or an episode run on another init state or seed changes what the
policy is handed and, through its actions, the rows. `slow`: ~2.5 min on 2 shared cores (six
LIBERO env builds, two spawned workers; the second run on them ~5 s of it).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from bench.progress import QUIET
from bench.sim import env as sim_env
from bench.sim import workers as pool
from bench.sim.batching import Batching
from bench.sim.frames import FrameGateMissed
from bench.sim.rollout import LIBERO, RolloutSpec, run_rollouts
from tests.sim_marks import needs_libero

# Every frame rendered, as before frames were gated: LIBERO's scenes with the plain env.
EVERY_STEP = LIBERO.__class__(sim_env.make_env, sim_env.task_descriptions,
                              sim_env.num_init_states, sim_env.reset_to, sim_env.observe)
SPEC = RolloutSpec("spatial", tasks=(0, 1), episodes_per_task=2, seed=0, max_steps=23,
                   n_action_steps=4)
RENDER = sim_env.RenderSettings(image_size=32)


def recorder(seen: list):
    def act(raw):
        state, image = raw["observation.state"], raw["observation.images.image"]
        wrist = raw["observation.images.wrist_image"]
        seen.extend((raw["task"][0], s.numpy().tobytes(), i.numpy().tobytes(), w.numpy().tobytes())
                    for s, i, w in zip(state, image, wrist))
        chunk = torch.zeros(len(state), 5, 7)  # 5 > n_action_steps: the slice is the loop's
        chunk[:, :, 0] = torch.sign(state[:, 1:2]) * 0.6
        chunk[:, :, 1] = (image.mean(dim=(1, 2, 3)) - wrist.mean(dim=(1, 2, 3)))[:, None] * 4
        chunk[:, :, 2] = torch.linspace(-0.5, 0.5, 5)
        chunk[:, :, 6] = -1.0
        return chunk
    return act


def rows(result: dict) -> list[dict]:
    """The per-episode rows without their wall time."""
    return [{k: v for k, v in e.items() if k != "seconds"} for e in result["episodes"]]


@pytest.mark.slow  # LIBERO scenes rendered in the simulator
@needs_libero
def test_gated_frames_and_workers_give_the_every_step_rollout_bit_for_bit():
    before, gated, pooled, again, built = [], [], [], [], []

    def rollout_env(*args, **kwargs):  # LIBERO's own, kept to read its forward gate's count
        built.append(sim_env.make_rollout_env(*args, **kwargs))
        return built[-1]

    base = run_rollouts(recorder(before), SPEC, progress=QUIET, render=RENDER, scenes=EVERY_STEP)
    alone = run_rollouts(recorder(gated), SPEC, progress=QUIET, render=RENDER,
                         scenes=dataclasses.replace(LIBERO, make_env=rollout_env))
    # the repeated forward was skipped, once a physics substep (25 a control step, and more)
    assert len(built) == 2 and all(env.forward_gate.skipped >= 25 * 23 * 2 for env in built)
    try:
        pool.discard_workers()
        workers = run_rollouts(recorder(pooled), SPEC, progress=QUIET, render=RENDER,
                               batching=Batching(workers=2))
        kept = pool.kept_pool()
        pids = [slot.process.pid for slot in kept.slots]
        # the next cell of the process: the same workers and their envs, reset to its episodes
        reused = run_rollouts(recorder(again), SPEC, progress=QUIET, render=RENDER,
                              batching=Batching(workers=2))
        assert pool.kept_pool() is kept and all(slot.process.is_alive() for slot in kept.slots)
        assert [slot.process.pid for slot in pool.kept_pool().slots] == pids
    finally:
        pool.discard_workers()
    assert rows(alone) == rows(base) and rows(workers) == rows(base) == rows(reused)
    assert [(e["task"], e["episode"], e["init_state"]) for e in base["episodes"]] == [
        (0, 0, 49), (0, 1, 48), (1, 0, 49), (1, 1, 48)]
    assert gated == before  # same observations, bytes, in the same order
    assert sorted(pooled) == sorted(before) == sorted(again) and len(before) == 4 * 6  # 6 reads
    assert workers["settings"]["env_mode"] == "2 workers"


@pytest.mark.slow  # LIBERO scenes rendered in the simulator
@needs_libero
def test_a_frame_read_but_not_rendered_fails_loudly():
    env = sim_env.make_rollout_env("spatial", 0, RENDER, max_steps=10)
    try:
        sim_env.reset_to(env, 49, 0)  # settles to control step 10, its frame rendered
        env.frame_gate.read_after(3)  # the gate renders step 13 only ...
        for _ in range(2):
            env.step(np.zeros(7))
        env.frame_gate.read_at = 12  # ... but the loop reads step 12's
        with pytest.raises(FrameGateMissed, match="control step 12"):
            env.frame_gate.check()
    finally:
        env.close()
