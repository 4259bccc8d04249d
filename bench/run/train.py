"""One training loop, read top to bottom: the projector of a graft, or a whole tiny policy.

The seed alone decides data order, flow-matching noise and time (each from its own generator), so
the same cell gives the same numbers whether features come from the cache or the encoder.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Callable, Iterable

import torch
from torch import Tensor

from backbones.base import Backbone
from bench.progress import STDERR, Progress, ProgressSink
from bench.results.provenance import stable_seed

# next_batch(step, frames) -> (raw batch, graft features or None)
BatchFn = Callable[[Tensor], tuple[dict, "dict[str, Tensor] | None"]]


class NonFiniteLoss(FloatingPointError):
    pass


@dataclass(frozen=True)
class FitConfig:
    steps: int
    batch_size: int
    lr: float
    weight_decay: float
    warmup_steps: int
    grad_clip: float
    log_every: int


def lr_factor(step: int, cfg: FitConfig) -> float:
    """Linear warm-up, then cosine decay to 0 over the remaining steps."""
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    span = max(1, cfg.steps - cfg.warmup_steps)
    return 0.5 * (1.0 + math.cos(math.pi * (step - cfg.warmup_steps) / span))


def batch_order(n_frames: int, cfg: FitConfig, seed: int) -> list[Tensor]:
    """Frame positions of each step: seeded permutations, epoch after epoch. (steps, B) long."""
    gen = torch.Generator().manual_seed(stable_seed(seed, "data-order"))
    order: list[Tensor] = []
    perm = torch.randperm(n_frames, generator=gen)
    cursor = 0
    for _ in range(cfg.steps):
        if cursor + cfg.batch_size > n_frames:
            perm, cursor = torch.randperm(n_frames, generator=gen), 0
        order.append(perm[cursor : cursor + cfg.batch_size])
        cursor += cfg.batch_size
    return order


def frozen_autocast(device: torch.device):
    """bf16 autocast on CUDA (the frozen backbone dominates the FLOPs); a no-op on CPU, so CPU
    numbers stay bit-identical. A fresh context per use."""
    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def fit(
    backbone: Backbone,
    params: Iterable[torch.nn.Parameter],
    frames: Tensor,
    next_batch: BatchFn,
    cfg: FitConfig,
    seed: int,
    feed=None,
    label: str = "train",
    progress: ProgressSink = STDERR,
) -> list[list[float]]:
    """Train `params` with the backbone's own loss. Returns the loss curve [[step, loss], ...]
    (every `log_every` steps, plus the first and last). Raises NonFiniteLoss naming the step."""
    params = [p for p in params if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, cfg))
    noise_gen = torch.Generator().manual_seed(stable_seed(seed, "flow-noise"))
    info = backbone.info
    bar = Progress(label, cfg.steps, progress)
    curve: list[list[float]] = []
    device = next(backbone.policy.parameters()).device
    for step, positions in enumerate(batch_order(len(frames), cfg, seed)):
        raw, features = next_batch(frames[positions])
        batch = backbone.preprocess(raw)
        size = len(positions)
        noise = torch.randn((size, info.chunk_size, info.max_action_dim), generator=noise_gen)
        flow_time = backbone.sample_time(size, noise_gen)
        if feed is not None:
            if features is not None:
                feed.bind(features)
            with backbone.image_embedder(feed), frozen_autocast(device):
                loss = backbone.loss(batch, noise, flow_time).mean()
            feed.assert_consumed()
        else:
            with frozen_autocast(device):
                loss = backbone.loss(batch, noise, flow_time).mean()
        if not torch.isfinite(loss):
            raise NonFiniteLoss(
                f"{label}: loss is {loss.item()} at step {step} of {cfg.steps}; "
                "lower the learning rate or check the inputs/normalisation stats for NaN/inf"
            )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if cfg.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        optimizer.step()
        scheduler.step()
        value = float(loss.detach())
        if step % cfg.log_every == 0 or step == cfg.steps - 1:
            curve.append([step, value])
        bar.update(step + 1, f"loss {value:.4f}")
    return curve
