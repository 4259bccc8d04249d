"""Closed-loop rollouts of any policy in LIBERO scenes through LeRobot's LiberoEnv.

`run_rollouts(act, spec)` runs `spec.episodes_per_task` episodes per task. Init states and env
seeds are a function of the spec alone, so every caller with the same spec (every cell of a
grid) meets the same scenes: paired comparisons. `act` sees exactly what the demonstrations
store (bench.sim.env.observe) and answers an action chunk in raw units; the first
`n_action_steps` actions are executed before it is asked again (LeRobot's action-queue
semantics). An episode succeeds when LIBERO's goal predicate holds (LiberoEnv's is_success).

Init states: episode e of a task uses official init state `n - 1 - e` (n = 50: counted from
the end), while the demonstrations use them from the start (0, 1, ...): the two sets are
disjoint as long as demos + rollouts per task <= 50.
"""

from __future__ import annotations

import hashlib
import sys
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch

from bench.sim import env as sim_env
from bench.stats import wilson_interval

ActFn = Callable[[dict], torch.Tensor]  # raw obs (batch of B) -> (B, T, 7) raw actions


@dataclass(frozen=True)
class RolloutSpec:
    suite: str  # "spatial" | "object"
    tasks: tuple[int, ...]  # LIBERO task ids
    episodes_per_task: int
    seed: int
    max_steps: int  # control steps per episode (LeRobot: 280 for spatial and object)
    n_action_steps: int  # chunk steps executed before re-planning

    def __post_init__(self):
        if self.suite not in sim_env.LIBERO_SUITES:
            raise ValueError(f"RolloutSpec.suite={self.suite!r}; choose one of "
                             f"{sorted(sim_env.LIBERO_SUITES)}")
        if self.episodes_per_task < 1 or self.max_steps < 1 or self.n_action_steps < 1:
            raise ValueError(f"RolloutSpec needs episodes_per_task, max_steps, n_action_steps >= 1;"
                             f" got {self.episodes_per_task}, {self.max_steps}, "
                             f"{self.n_action_steps}")


def rollout_init_state(episode: int, num_init_states: int) -> int:
    """Official init state of rollout episode `episode` (from the end of the list)."""
    if episode >= num_init_states:
        raise ValueError(f"rollout episode {episode}: only {num_init_states} init states")
    return num_init_states - 1 - episode


def rollout_env_seed(seed: int, task: int, episode: int) -> int:
    digest = hashlib.sha256(f"rollout:{seed}:{task}:{episode}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def run_episode(act: ActFn, env, init_state: int, env_seed: int, max_steps: int,
                n_action_steps: int, description: str) -> dict:
    """One closed-loop episode from `init_state`; {"init_state", "success", "steps", "seconds"}."""
    start = time.perf_counter()
    obs = sim_env.reset_to(env, init_state, env_seed)
    on_reset = getattr(act, "on_reset", None)
    if on_reset is not None:  # privileged policies (the scripted expert) read the sim state
        on_reset([env])
    success, steps = False, 0
    while steps < max_steps and not success:
        raw = sim_env.observe([obs], [description])
        with torch.inference_mode():
            chunk = act(raw)
        chunk = torch.as_tensor(chunk).detach().float().cpu()
        if chunk.ndim != 3 or chunk.shape[0] != 1 or chunk.shape[2] != 7:
            raise ValueError(f"act returned shape {tuple(chunk.shape)}; expected (B=1, T, 7) raw "
                             "actions")
        for action in chunk[0, :n_action_steps].numpy().astype(np.float64):
            obs, _, _, _, info = env.step(action)
            steps += 1
            if info.get("is_success", False):
                success = True
            if success or steps >= max_steps:
                break
    return {"init_state": int(init_state), "success": bool(success), "steps": steps,
            "seconds": round(time.perf_counter() - start, 2)}


def run_rollouts(act: ActFn, spec: RolloutSpec, progress: bool = True,
                 render: sim_env.RenderSettings | None = None) -> dict:
    """Run `spec` with policy `act`; per-episode successes, rates and Wilson 95% intervals.

    act(raw) -> (B, T, 7) raw actions, raw = {"observation.images.image": (B, 3, H, W) float32
    [0, 1], "observation.images.wrist_image": same, "observation.state": (B, 8) float32,
    "task": list[str]}; B = 1 here (one env stepped at a time: 2 cores gain nothing from more).
    """
    render = render or sim_env.RenderSettings()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # 2 shared cores: one thread each for sim and policy is faster
    try:
        episodes, seconds = _run_all(act, spec, progress, render)
    finally:
        torch.set_num_threads(threads)
    return summarise(episodes, spec, render, seconds)


def _run_all(act: ActFn, spec: RolloutSpec, progress: bool,
             render: sim_env.RenderSettings) -> tuple[list[dict], float]:
    descriptions = sim_env.task_descriptions(spec.suite)
    episodes = []
    start = time.perf_counter()
    for task in spec.tasks:
        env = sim_env.make_env(spec.suite, task, render, max_steps=spec.max_steps)
        try:
            for episode in range(spec.episodes_per_task):
                init_state = rollout_init_state(episode, sim_env.num_init_states(env))
                row = {"task": task, "episode": episode, **run_episode(
                    act, env, init_state, rollout_env_seed(spec.seed, task, episode),
                    spec.max_steps, spec.n_action_steps, descriptions[task])}
                episodes.append(row)
                if progress:
                    print(f"[rollout] {spec.suite} task {task} episode {episode} "
                          f"(init {row['init_state']}): {'success' if row['success'] else 'failure'}"
                          f" in {row['steps']} steps ({row['seconds']:.1f} s)",
                          file=sys.stderr, flush=True)
        finally:
            env.close()
    return episodes, time.perf_counter() - start


def replay(actions: np.ndarray, suite: str, task: int, init_state: int, env_seed: int,
           render: sim_env.RenderSettings | None = None) -> dict:
    """Execute recorded raw actions (T, 7) open-loop from `init_state`; run_episode's dict."""
    from bench.sim.expert import ReplayPolicy

    render = render or sim_env.RenderSettings()
    env = sim_env.make_env(suite, task, render, max_steps=len(actions))
    try:
        description = sim_env.task_descriptions(suite)[task]
        return run_episode(ReplayPolicy(actions), env, init_state, env_seed, len(actions), 1,
                           description)
    finally:
        env.close()


def summarise(episodes: list[dict], spec: RolloutSpec, render: sim_env.RenderSettings,
              seconds: float) -> dict:
    """The result dict of run_rollouts from its episode rows."""
    wins = sum(e["success"] for e in episodes)
    per_task = {}
    for task in spec.tasks:
        rows = [e for e in episodes if e["task"] == task]
        k = sum(e["success"] for e in rows)
        per_task[str(task)] = {"successes": k, "episodes": len(rows),
                               "success_rate": k / len(rows) if rows else 0.0,
                               "ci95": list(wilson_interval(k, len(rows)))}
    return {
        "episodes": episodes,
        "success_rate": wins / len(episodes) if episodes else 0.0,
        "per_task": per_task,
        "ci95": list(wilson_interval(wins, len(episodes))),
        "settings": {
            "spec": asdict(spec),
            "libero_suite": sim_env.LIBERO_SUITES[spec.suite],
            "render": render.as_dict(),
            "mujoco_gl": __import__("os").environ.get("MUJOCO_GL"),
            "control_hz": sim_env.CONTROL_HZ,
            "settle_steps": sim_env.SETTLE_STEPS,
            "hard_reset": False,
            "init_states": "official LIBERO init states, episode e -> n-1-e",
            "image_orientation": "LeRobot LIBERO env processor (rotated 180 degrees)",
            "seconds": round(seconds, 1),
        },
    }
