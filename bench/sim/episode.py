"""One closed-loop episode's parts, shared by the in-process loop (bench.sim.rollout) and the
worker processes (bench.sim.workers), so both step, read and record an episode alike."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
import torch

ActFn = Callable[[dict], torch.Tensor]  # raw obs (batch of B) -> (B, T, 7) raw actions

def rollout_init_state(episode: int, num_init_states: int) -> int:
    """Official init state of rollout episode `episode` (from the end of the list)."""
    if episode >= num_init_states:
        raise ValueError(f"rollout episode {episode}: only {num_init_states} init states")
    return num_init_states - 1 - episode


def reads_nothing(env, steps) -> None:
    """A test's scenes render what they like: nothing to gate."""


def next_actions(act: ActFn, raw: dict, n_action_steps: int) -> np.ndarray:
    """The policy's chunk for one observation: its first `n_action_steps` actions, (T, 7)
    float64 (what env.step receives)."""
    with torch.inference_mode():
        chunk = act(raw)
    chunk = torch.as_tensor(chunk).detach().float().cpu()
    if chunk.ndim != 3 or chunk.shape[0] != 1 or chunk.shape[2] != 7:
        raise ValueError(f"act returned shape {tuple(chunk.shape)}; expected (B=1, T, 7) raw "
                         "actions")
    return chunk[0, :n_action_steps].numpy().astype(np.float64)


def execute_chunk(env, actions: np.ndarray, steps_left: int,
                  read_after: Callable = reads_nothing) -> tuple:
    """Step `actions` (T, 7) until they run out, the goal holds or `steps_left` is spent;
    (last observation, steps taken, success). Frames are rendered only where the loop will
    read them (`read_after(env, steps)`, Scenes.read_after): after the chunk's last action,
    unless the episode ends on it."""
    read_after(env, len(actions) if len(actions) < steps_left else None)
    obs, steps = None, 0
    for action in actions[:steps_left]:
        obs, _, _, _, info = env.step(action)
        steps += 1
        if info.get("is_success", False):
            return obs, steps, True
    return obs, steps, False


def episode_row(init_state: int, success: bool, steps: int, start: float) -> dict:
    return {"init_state": int(init_state), "success": bool(success), "steps": steps,
            "seconds": round(time.perf_counter() - start, 2)}
