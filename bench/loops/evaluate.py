"""Offline action MSE: sampled chunks vs. ground truth on held-out windows.

- windows: every `eval_stride` frames of held-out episodes (whole episodes, per task, split seed
  independent of the cell): every cell of a backbone x suite scores identical windows;
- the backbone's own sampler, default step count, with noise fixed per window (common random
  numbers): the noise of a window depends only on (eval_noise_seed, window frame id);
- only the real action dims (LIBERO: 7) and only real chunk steps (action_is_pad masked);
- normalised (the policy's action space) and raw units; per window, per task, per horizon step;
- for the offline measures (bench.analysis.offline_measures): per window over only the steps the
  policy executes before it replans, and which windows are task-critical (bench.suites.critical).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import torch
from torch import Tensor

from backbones.base import Backbone
from bench.results.provenance import stable_seed
from bench.results.record import NORMALIZED, RAW, Scores, task_score
from bench.suites.critical import critical_rule, critical_windows
from bench.suites.windows import raw_batch
from bench.loops.train import frozen_autocast

# features_for(window positions, frames) -> {camera: (B, N, C)} for a graft, else None.
FeaturesFn = Callable[[Tensor, Tensor], "dict[str, Tensor] | None"]
# images_for(window positions, frames, raw images) -> images the policy sees (native controls).
ImagesFn = Callable[[Tensor, Tensor, dict], dict]


def window_noise(window_ids: Tensor, chunk: int, width: int, seed: int) -> Tensor:
    """(B, chunk, width) float32: each window's noise from its own generator (CRN)."""
    out = torch.empty((len(window_ids), chunk, width))
    for i, wid in enumerate(window_ids.tolist()):
        gen = torch.Generator().manual_seed(stable_seed(seed, "window", wid))
        out[i] = torch.randn((chunk, width), generator=gen)
    return out


def masked_sq_error(pred: Tensor, target: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Per-window mean squared error (B,) and per-step summed error (B, T) over real steps.

    pred/target: (B, T, A); valid: (B, T) bool (False on padded chunk steps)."""
    sq = (pred - target).pow(2).mean(dim=-1) * valid
    per_window = sq.sum(dim=1) / valid.sum(dim=1).clamp(min=1)
    return per_window, sq


def executed_steps(backbone: Backbone) -> int:
    """Chunk steps the cell's policy executes before it replans: the closed loop
    (bench.cell.rollouts) runs the whole chunk, as LeRobot's n_action_steps = chunk_size in
    every policy built here, so offline scoring and rollouts read this one number."""
    return backbone.info.chunk_size


def prefix_window_error(per_step: Tensor, valid: Tensor, n_steps: int) -> Tensor:
    """(B,) mean squared error over each window's first `n_steps` real steps.

    per_step: (B, T) masked_sq_error's per-step error; valid: (B, T) bool. With n_steps = T it is
    masked_sq_error's per-window error, bit for bit (the same reductions over the same values)."""
    head = valid[:, :n_steps]
    return per_step[:, :n_steps].sum(dim=1) / head.sum(dim=1).clamp(min=1)


@torch.no_grad()
def sample_grafted(backbone: Backbone, batch: dict, noise: Tensor, feed=None,
                   features: dict | None = None) -> Tensor:
    """The backbone's sampler, with `feed` spliced in at the graft point when given (bound to
    `features` first unless the feed runs a tower itself); (B, chunk, A) normalised."""
    device = noise.device
    if feed is None:
        with frozen_autocast(device):
            return backbone.sample_actions(batch, noise)
    if features is not None:
        feed.bind(features)
    with backbone.image_embedder(feed), frozen_autocast(device):
        pred = backbone.sample_actions(batch, noise)
    feed.assert_consumed()
    return pred


def score(
    backbone: Backbone,
    suite,
    windows: Tensor,
    batch_size: int,
    noise_seed: int,
    feed=None,
    features_for: FeaturesFn | None = None,
    images_for: ImagesFn | None = None,
) -> Scores:
    """Offline action MSE of the backbone (with `feed` spliced in when given) on `windows`."""
    info = backbone.info
    chunk = info.chunk_size
    err = {NORMALIZED: [], RAW: []}
    executed = {NORMALIZED: [], RAW: []}
    n_exec = executed_steps(backbone)
    horizon_sum = {NORMALIZED: torch.zeros(chunk), RAW: torch.zeros(chunk)}
    horizon_n = torch.zeros(chunk)
    device = next(backbone.policy.parameters()).device
    for start in range(0, len(windows), batch_size):
        positions = torch.arange(start, min(start + batch_size, len(windows)))
        frames = windows[positions]
        raw = raw_batch(suite, frames, chunk, with_images=True)
        if images_for is not None:
            images = images_for(positions, frames, {k: raw[k] for k in suite.camera_keys})
            raw.update(images)
        batch = backbone.preprocess(raw)
        noise = window_noise(frames, chunk, info.max_action_dim, noise_seed)
        features = features_for(positions, frames) if feed is not None and features_for else None
        pred = sample_grafted(backbone, batch, noise.to(device), feed, features)
        target_raw = raw["action"]
        valid = ~raw["action_is_pad"]
        pred = pred[..., : target_raw.shape[-1]].float().cpu()
        pairs = {
            NORMALIZED: (pred, backbone.normalize_actions(target_raw).float().cpu()),
            RAW: (backbone.unnormalize_actions(pred).float().cpu(), target_raw),
        }
        for space, (p, t) in pairs.items():
            per_window, per_step = masked_sq_error(p, t, valid)
            err[space].append(per_window)
            executed[space].append(prefix_window_error(per_step, valid, n_exec))
            horizon_sum[space] += per_step.sum(dim=0)
        horizon_n += valid.sum(dim=0)
    per_window = {k: torch.cat(v) for k, v in err.items()}
    scores = summarise(suite, windows, per_window, {k: v / horizon_n.clamp(min=1)
                                                    for k, v in horizon_sum.items()})
    return with_measure_inputs(scores, suite, windows, chunk, n_exec,
                               {k: torch.cat(v) for k, v in executed.items()})


def with_measure_inputs(scores: Scores, suite, windows: Tensor, chunk: int, n_action_steps: int,
                        executed: dict[str, Tensor]) -> Scores:
    """`scores` with what the offline measures read: the chunk and executed step counts, the
    per-window error over the executed steps (kept only when it is not per_window itself) and
    the critical-window flags with their rule."""
    kept = ({k: v.tolist() for k, v in executed.items()} if n_action_steps < chunk else None)
    critical = critical_windows(suite, windows, chunk)  # None: no gripper in these actions
    return dataclasses.replace(
        scores, chunk_length=chunk, n_action_steps=n_action_steps, per_window_executed=kept,
        window_critical=critical.tolist() if critical is not None else None,
        critical_rule=critical_rule() if critical is not None else None)


def summarise(suite, windows: Tensor, per_window: dict[str, Tensor],
                per_horizon: dict[str, Tensor]) -> Scores:
    """The score part of a record: cell MSE, per window, per task, per horizon step."""
    tasks = suite.task_index[windows]
    per_task = {}
    for t in sorted(set(tasks.tolist())):
        sel = tasks == t
        per_task[suite.tasks[t]] = task_score({k: float(v[sel].mean()) for k, v in per_window.items()},
                                              int(sel.sum()))
    for space, values in per_window.items():
        if not torch.isfinite(values).all():
            raise FloatingPointError(f"non-finite {space} action error on held-out windows")
    return Scores(
        # The cell MSE is the mean over windows (each window: mean over its real steps x dims).
        mse={k: float(v.mean()) for k, v in per_window.items()},
        per_window={k: v.tolist() for k, v in per_window.items()},
        window_ids=windows.tolist(),
        n_windows=len(windows),
        window_task=tasks.tolist(),
        window_episode=suite.episode_index[windows].tolist(),
        tasks=list(suite.tasks),
        per_task=per_task,
        per_horizon={k: v.tolist() for k, v in per_horizon.items()},
    )


def derangement(n: int, seed: int) -> Tensor:
    """A fixed permutation of range(n) with no fixed point (shuffled-image control). (n,) long."""
    if n < 2:
        raise ValueError("a derangement needs at least 2 windows")
    gen = torch.Generator().manual_seed(stable_seed(seed, "derangement"))
    while True:
        perm = torch.randperm(n, generator=gen)
        if not (perm == torch.arange(n)).any():
            return perm
