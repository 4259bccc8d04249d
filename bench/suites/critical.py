"""Task-critical held-out windows: those whose scored span nears a gripper open/close event.

The rule (bench.analysis.offline_measures' critical-interval MSE reads the flags it gives):
- an EVENT is a frame f whose gripper action's sign differs from frame f-1's in the same
  episode (sign: > 0 closes, <= 0 opens: LIBERO's -1 open / +1 close);
- a window starting at frame s is CRITICAL when its scored span, frames s .. s+chunk-1 clipped
  at its episode's last frame (the real steps its MSE counts), holds a frame within
  +-CRITICAL_MARGIN frames of an event of its episode.

Grasps and releases are where a closed loop succeeds or fails (a late close misses the object,
an early open drops it), while free-space motion forgives error: the Critical Interval MSE
study (arXiv 2606.29898) found MSE restricted to such segments tracked success better.
"""

from __future__ import annotations

import torch
from torch import Tensor

from bench.suites.windows import episode_last_frame

# LIBERO's action is (dx, dy, dz, dax, day, daz, gripper): the gripper command is the last
# dimension (ondisk.libero_format's action names).
GRIPPER_DIM = 6
# Frames either side of an event that still count as the event: 5 frames is 0.25 s at LIBERO's
# 20 Hz, about the time the fingers take to close or open, so the approach just before contact
# and the lift just after it count too, and free-space motion does not.
CRITICAL_MARGIN = 5


def critical_rule() -> dict:
    """The rule's parameters, stored beside the flags (records under another rule never mix)."""
    return {"gripper_dim": GRIPPER_DIM, "margin": CRITICAL_MARGIN}


def gripper_events(action: Tensor, episode_index: Tensor) -> Tensor:
    """(N,) bool: frame f's gripper sign differs from frame f-1's of the same episode.

    action: (N, A) raw actions; episode_index: (N,) episode of every frame (contiguous runs)."""
    closed = action[:, GRIPPER_DIM] > 0
    event = torch.zeros(len(action), dtype=torch.bool)
    same_episode = episode_index[1:] == episode_index[:-1]
    event[1:] = (closed[1:] != closed[:-1]) & same_episode
    return event


def has_gripper(suite) -> bool:
    """The rule reads LIBERO's action layout (gripper last of 7); a user's dataset with fewer
    action dimensions has no gripper there (its records simply lack the measure)."""
    return suite.action.dim() == 2 and suite.action.shape[1] > GRIPPER_DIM


def critical_windows(suite, windows: Tensor, chunk: int,
                     margin: int = CRITICAL_MARGIN) -> Tensor | None:
    """(W,) bool: whether each window (global start frame, (W,) long) is critical (module rule);
    None where the suite's actions have no gripper dimension (has_gripper)."""
    if not has_gripper(suite):
        return None
    windows = torch.as_tensor(windows, dtype=torch.long).reshape(-1)
    event = gripper_events(suite.action, suite.episode_index)
    # Events dilated by the margin, kept inside their own episode: frame f is "near" when an
    # event of its episode lies in [f - margin, f + margin].
    n = len(event)
    near = torch.zeros(n, dtype=torch.bool)
    for e in torch.nonzero(event).flatten().tolist():
        lo, hi = max(0, e - margin), min(n - 1, e + margin)
        same = suite.episode_index[lo:hi + 1] == suite.episode_index[e]
        near[lo:hi + 1] |= same
    last = episode_last_frame(suite)[windows]
    out = torch.zeros(len(windows), dtype=torch.bool)
    for i, (start, end) in enumerate(zip(windows.tolist(), last.tolist())):
        out[i] = bool(near[start:min(start + chunk - 1, end) + 1].any())
    return out
