"""Batched closed-loop rollouts: B envs of one task in LeRobot's own gym vector env.

`run_batched(act, spec, batch=B)` rolls out the same episodes as B = 1 (bench.sim.rollout): the
same init states (episode e -> n-1-e) and env seeds, so cells stay paired, and the same
per-episode rows, in the same order. What changes is how they are run: LeRobot 0.6.1's
`create_libero_envs` builds the B LiberoEnv factories of a task and wraps them in a gymnasium
SyncVectorEnv (one process) or AsyncVectorEnv (one worker process and EGL context per env, as
lerobot-eval does); every step the policy is called ONCE for all slots whose action chunk is
used up, and a slot whose episode ended is reset at once to the next episode of the queue, so
an early success frees its slot instead of idling until the slowest episode ends.

Outcomes equal B = 1 for a policy whose rows do not depend on the rest of the batch (the
graft policies' sampler noise is seeded per observation row; their batched matmuls may differ
from single-row ones in the last float bits). Slots left idle when the queue is empty step a
no-op action (a gym vector env steps all its envs); that is the tail cost of batching.
"""

from __future__ import annotations

import contextlib
import io
import time
from dataclasses import dataclass
from functools import partial
from typing import Callable

import numpy as np
import torch

from bench.sim import env as sim_env

ENV_MODES = ("sync", "async")  # gymnasium SyncVectorEnv / AsyncVectorEnv


@dataclass(frozen=True)
class VectorScenes:
    """What the batched loop needs from a simulator: LIBERO's by default; a test passes its own."""

    # (suite, task, render, max_steps, batch, mode) -> gymnasium VectorEnv whose sub-envs accept
    # reset(seed=, options={"init_states": [one per slot]}): make_paired
    make_vector_env: Callable
    descriptions: Callable[[str], list[str]]  # suite -> instruction per task id
    num_init_states: int  # official init states per task (LIBERO: 50)
    observe: Callable  # (batched raw observation, [instruction]) -> what `act` receives


def make_paired(env, slot: int, reset_to: Callable):
    """`env` as slot `slot` of a vector env: reset(options={"init_states": [...]}) resets it to
    ITS init state through `reset_to` (the B = 1 reset: gripper integrator zeroed, seeded); a
    reset without them (the vector env's autoreset of an idle slot) is the env's plain reset."""
    import gymnasium as gym  # lazily: the module imports without the libero extra

    class _PairedReset(gym.Wrapper):
        def reset(self, *, seed=None, options=None):
            if not options or "init_states" not in options:
                return self.env.reset(seed=seed)
            obs = reset_to(self.env, int(options["init_states"][slot]), seed)
            return obs, {"is_success": False}

    return _PairedReset(env)


def _libero_slot(factory: Callable, slot: int, render: sim_env.RenderSettings):
    """One slot's env, built inside its worker: LeRobot's factory, our render settings."""
    sim_env.configure()  # a spawned worker has not run it
    env = factory()
    env._ensure_env()
    sim_env.apply_render_settings(env, render)
    return make_paired(env, slot, sim_env.reset_to)


def make_libero_vector_env(suite: str, task: int, render: sim_env.RenderSettings, max_steps: int,
                           batch: int, mode: str):
    """LeRobot's `create_libero_envs` for one task, `batch` envs, sync or async."""
    import gymnasium as gym

    if mode not in ENV_MODES:
        raise ValueError(f"vector env mode {mode!r}; choose one of {ENV_MODES}")
    sim_env.task_suite(suite)  # configures LIBERO before lerobot.envs.libero imports it
    from lerobot.envs.libero import create_libero_envs

    def env_cls(factories):
        slots = [partial(_libero_slot, f, i, render) for i, f in enumerate(factories)]
        reset = gym.vector.AutoresetMode.NEXT_STEP
        if mode == "sync":
            return gym.vector.SyncVectorEnv(slots, autoreset_mode=reset)
        # Spawned, not forked: a fork of this multi-threaded (torch) process deadlocked its
        # workers while they built their envs (measured 2026-12-03: 3 workers idle for 5 min).
        return gym.vector.AsyncVectorEnv(slots, autoreset_mode=reset, context="spawn")

    name = sim_env.LIBERO_SUITES[suite]
    with contextlib.redirect_stdout(io.StringIO()):  # it prints a line per task built
        envs = create_libero_envs(
            name, n_envs=batch, env_cls=env_cls, camera_name=list(sim_env.CAMERA_MAPPING),
            init_states=True, episode_length=max_steps,
            camera_name_mapping=sim_env.CAMERA_MAPPING,
            gym_kwargs={"task_ids": [task], "obs_type": "pixels_agent_pos",
                        "observation_width": render.image_size,
                        "observation_height": render.image_size,
                        "num_steps_wait": sim_env.SETTLE_STEPS,
                        "control_freq": sim_env.CONTROL_HZ,
                        "hard_reset": False})  # soft resets keep the render settings
    return envs[name][task]


LIBERO_VECTOR = VectorScenes(make_libero_vector_env, sim_env.task_descriptions, 50,
                             sim_env.observe_batched)


@dataclass
class _Slot:
    task: int
    episode: int
    init_state: int
    started: float
    steps: int = 0
    success: bool = False
    queue: list | None = None  # actions left of the current chunk

    def named(self) -> str:
        return f"episode {self.episode} (init state {self.init_state})"

    def row(self) -> dict:
        return {"task": self.task, "episode": self.episode, "init_state": self.init_state,
                "success": self.success, "steps": self.steps,
                "seconds": round(time.perf_counter() - self.started, 2)}


def rows_of(tree, rows: np.ndarray):
    """The `rows` of every array of a nested observation dict."""
    if isinstance(tree, dict):
        return {k: rows_of(v, rows) for k, v in tree.items()}
    return np.asarray(tree)[rows]


def ask_policy(act, raw: dict) -> torch.Tensor:
    """act(raw) as (B, T, 7) float32 on the CPU, B = the rows of `raw`; a wrong shape raises."""
    with torch.inference_mode():
        chunk = torch.as_tensor(act(raw)).detach().float().cpu()
    rows = len(raw["task"])
    if chunk.ndim != 3 or chunk.shape[0] != rows or chunk.shape[2] != 7:
        raise ValueError(f"act returned shape {tuple(chunk.shape)}; expected (B={rows}, T, 7) "
                         "raw actions")
    return chunk


class _TaskBatch:
    """The slots of one task's vector env: which episode each runs, its chunk, its count."""

    def __init__(self, venv, width: int, spec, task: int, crash: Callable):
        self.venv, self.spec, self.task, self.crash = venv, spec, task, crash
        self.slots: list[_Slot | None] = [None] * width
        self.inits = [0] * width  # each slot's latest init state (PairedReset reads its own)
        self.obs = None

    def where(self, slots: list[int]) -> str:
        return (f"{self.spec.suite} task {self.task} "
                + ", ".join(self.slots[i].named() for i in slots))

    def start(self, free: list[int], planned: list[tuple[int, int, int]]) -> None:
        """Reset slots `free` to the next planned (episode, init state, env seed) each."""
        seeds = [0] * len(self.slots)
        for i in free:
            episode, self.inits[i], seeds[i] = planned.pop(0)
            self.slots[i] = _Slot(self.task, episode, self.inits[i], time.perf_counter())
        mask = np.zeros(len(self.slots), dtype=bool)
        mask[free] = True
        # The vector env hands back every slot's observation (the others' unchanged).
        self.obs, _ = self.crash(lambda: self.venv.reset(seed=seeds, options={
            "reset_mask": mask, "init_states": list(self.inits)}), self.where(free) + ": reset")

    def plan_chunks(self, act, observe: Callable, description: str) -> None:
        """One policy call for every running slot whose chunk is used up."""
        ask = [i for i, s in enumerate(self.slots) if s is not None and not s.queue]
        if not ask:
            return
        chunk = self.crash(lambda: ask_policy(act, observe(
            rows_of(self.obs, np.array(ask)), [description] * len(ask))),
            self.where(ask) + ": the policy")
        for row, i in enumerate(ask):
            self.slots[i].queue = list(chunk[row, :self.spec.n_action_steps].numpy()
                                       .astype(np.float64))

    def step(self) -> list[_Slot]:
        """Step every env once; the slots whose episode ended (success or max_steps), freed."""
        active = [i for i, s in enumerate(self.slots) if s is not None]
        actions = np.zeros((len(self.slots), 7))  # idle slots: a no-op, gripper open
        actions[:, 6] = -1.0
        for i in active:
            actions[i] = self.slots[i].queue.pop(0)
        self.obs, _, _, _, info = self.crash(lambda: self.venv.step(actions), self.where(active))
        won = np.asarray(info.get("is_success", np.zeros(len(self.slots))), dtype=bool)
        ended = []
        for i in active:
            slot = self.slots[i]
            slot.steps, slot.success = slot.steps + 1, bool(won[i])
            if slot.success or slot.steps >= self.spec.max_steps:
                ended.append(i)
        return ended


def run_task_batched(act, spec, task: int, planned: list[tuple[int, int, int]],
                     description: str, render, batching, scenes: VectorScenes,
                     done: Callable[[dict], None], crash: Callable[[Callable, str], object]):
    """Roll out `planned` (episode, init state, env seed) of `task` over min(batching.size, episodes)
    slots of a vector env (`batching`: bench.sim.rollout.Batching), refilling a slot as its
    episode ends; `done(row)` for each."""
    if getattr(act, "on_reset", None) is not None:
        raise ValueError("a privileged policy (on_reset: the scripted expert, a replay) reads "
                         "its env in-process; roll it out with batch 1")
    planned = list(planned)
    width, mode = min(batching.size, len(planned)), batching.mode
    venv = crash(lambda: scenes.make_vector_env(spec.suite, task, render, spec.max_steps, width,
                                                mode),
                 f"{spec.suite} task {task}: building its {width} {mode} envs")
    try:
        slots = _TaskBatch(venv, width, spec, task, crash)
        slots.start(list(range(width)), planned)
        while any(s is not None for s in slots.slots):
            slots.plan_chunks(act, scenes.observe, description)
            ended = slots.step()
            for i in ended:
                done(slots.slots[i].row())
                slots.slots[i] = None
            refill = ended[:len(planned)]  # slots that end together share what is left
            if refill:
                slots.start(refill, planned)
    finally:
        venv.close()
