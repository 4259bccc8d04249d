"""Held-out episodes, evaluation windows, action chunks and raw batches: pure functions of a Suite.

A "frame" is a global frame index: a row of the suite's per-frame tensors (0 <= f < N).
Episodes are stored as contiguous runs (checked when a suite is loaded).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ondisk.libero_format import STATE_KEY
from bench.suites.base import Suite


def episode_tasks(suite: Suite) -> dict[int, int]:
    """{episode index: task index}, from each episode's first frame."""
    first = suite.frame_index == 0
    return dict(zip(suite.episode_index[first].tolist(), suite.task_index[first].tolist()))


def heldout_split(suite: Suite, split_seed: int, per_task: int) -> tuple[list[int], list[int]]:
    """(train_episodes, heldout_episodes), both sorted: `per_task` whole episodes held out per task.

    Drawn with numpy default_rng((split_seed, task_index)) per task, so the split depends only on
    the suite and `split_seed` (never on a cell seed), and one task's draw never shifts another's.
    """
    by_task: dict[int, list[int]] = {}
    for episode, task in sorted(episode_tasks(suite).items()):
        by_task.setdefault(task, []).append(episode)
    heldout: list[int] = []
    for task, episodes in sorted(by_task.items()):
        if len(episodes) <= per_task:
            raise ValueError(
                f"suite {suite.name!r} task {task} ({suite.tasks[task]!r}) has {len(episodes)} "
                f"episodes, needs more than heldout per_task={per_task} to keep training data"
            )
        rng = np.random.default_rng((split_seed, task))
        heldout += rng.choice(episodes, size=per_task, replace=False).tolist()
    heldout_set = set(heldout)
    train = [e for eps in by_task.values() for e in eps if e not in heldout_set]
    return sorted(train), sorted(heldout)


def episode_frames(suite: Suite, episodes: list[int]) -> Tensor:
    """(M,) int64 sorted global frame indices of all frames of `episodes`."""
    mask = torch.isin(suite.episode_index, torch.as_tensor(list(episodes), dtype=torch.long))
    return torch.nonzero(mask).flatten()


def eval_windows(suite: Suite, episodes: list[int], stride: int) -> Tensor:
    """(W,) int64 sorted global frame indices at frames 0, stride, 2*stride, ... of each episode."""
    if stride < 1:
        raise ValueError(f"eval stride must be >= 1, got {stride}")
    frames = episode_frames(suite, episodes)
    return frames[suite.frame_index[frames] % stride == 0]


def episode_last_frame(suite: Suite) -> Tensor:
    """(N,) int64: for every frame, the global index of its episode's last frame."""
    _, counts = torch.unique_consecutive(suite.episode_index, return_counts=True)
    ends = torch.cumsum(counts, 0) - 1
    return torch.repeat_interleave(ends, counts)


def action_chunks(suite: Suite, frames: Tensor, chunk: int) -> tuple[Tensor, Tensor]:
    """(actions (B, chunk, 7) float32 raw units, is_pad (B, chunk) bool) starting at `frames` (B,).

    actions[b, k] is the action at frame f+k of the same episode; past the episode's end the last
    action is repeated and is_pad is True (LeRobot's delta_timestamps convention).
    """
    frames = torch.as_tensor(frames, dtype=torch.long).reshape(-1)
    wanted = frames[:, None] + torch.arange(chunk)[None, :]
    last = episode_last_frame(suite)[frames][:, None]
    is_pad = wanted > last
    return suite.action[torch.minimum(wanted, last)], is_pad


def raw_batch(suite: Suite, frames: Tensor, chunk: int, with_images: bool = True) -> dict:
    """The raw batch of backbones/base.py for windows starting at `frames` (B,).

    {camera: (B, 3, H, W) float32 [0, 1] (when with_images), "observation.state": (B, 8) float32,
     "action": (B, chunk, 7) float32, "action_is_pad": (B, chunk) bool, "task": list[str] (B)}
    """
    frames = torch.as_tensor(frames, dtype=torch.long).reshape(-1)
    actions, is_pad = action_chunks(suite, frames, chunk)
    batch = suite.images(frames) if with_images else {}
    batch[STATE_KEY] = suite.state[frames]
    batch["action"] = actions
    batch["action_is_pad"] = is_pad
    batch["task"] = [suite.tasks[t] for t in suite.task_index[frames].tolist()]
    return batch
