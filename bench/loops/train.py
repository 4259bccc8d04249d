"""One training loop, read top to bottom: the projector of a graft, or a whole tiny policy.

The seed alone decides data order, flow-matching noise and time (each from its own generator), so
the same cell gives the same numbers whether features come from the cache or the encoder.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Sequence

import torch
from torch import Tensor

from backbones.base import Backbone
from bench.progress import Progress, ProgressSink
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


def batch_order(n_frames: int, cfg: FitConfig, seed: int) -> Iterator[Tensor]:
    """Frame positions of each step, (B,) long, one step at a time: seeded permutations, epoch
    after epoch. Streamed: memory stays one permutation whatever cfg.steps is."""
    gen = torch.Generator().manual_seed(stable_seed(seed, "data-order"))
    perm = torch.randperm(n_frames, generator=gen)
    cursor = 0
    for _ in range(cfg.steps):
        if cursor + cfg.batch_size > n_frames:
            perm, cursor = torch.randperm(n_frames, generator=gen), 0
        yield perm[cursor : cursor + cfg.batch_size]
        cursor += cfg.batch_size


def frozen_autocast(device: torch.device):
    """bf16 autocast on CUDA (the frozen backbone dominates the FLOPs); a no-op on CPU, so CPU
    numbers stay bit-identical. A fresh context per use."""
    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def make_optimizer(params: Iterable[torch.nn.Parameter], cfg: FitConfig,
                   other_lrs: Sequence[tuple[Iterable[torch.nn.Parameter], float]] = ()):
    """AdamW over the trainable `params` (+ `other_lrs` groups at their own rate) under the
    warm-up/cosine schedule; (optimizer, scheduler, every parameter the clip sees)."""
    params = [p for p in params if p.requires_grad]
    groups = [{"params": params}] + [{"params": [q for q in group if q.requires_grad], "lr": lr}
                                     for group, lr in other_lrs]
    optimizer = torch.optim.AdamW(groups, lr=cfg.lr, weight_decay=cfg.weight_decay)
    clipped = [q for group in groups for q in group["params"]]
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, cfg))
    return optimizer, scheduler, clipped


def noise_generator(seed: int) -> torch.Generator:
    """The generator of a cell's flow-matching noise and time (its data order has its own)."""
    return torch.Generator().manual_seed(stable_seed(seed, "flow-noise"))


def draw_step(backbone: Backbone, frames: Tensor, next_batch: BatchFn,
              noise_gen: torch.Generator) -> tuple[dict, "dict[str, Tensor] | None", Tensor, Tensor]:
    """One step's draws, in the order `fit` has always made them: the batch (and its features),
    then the noise, then the flow time. (raw batch, features, noise, time)."""
    info = backbone.info
    raw, features = next_batch(frames)
    size = len(frames)
    noise = torch.randn((size, info.chunk_size, info.max_action_dim), generator=noise_gen)
    return raw, features, noise, backbone.sample_time(size, noise_gen)


def clip_and_step(params: list[torch.nn.Parameter], optimizer, scheduler, cfg: FitConfig) -> None:
    """Clip the gradients of `params` (when cfg asks), then one optimiser and schedule step."""
    if cfg.grad_clip > 0:
        torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
    optimizer.step()
    scheduler.step()


def fit(
    backbone: Backbone,
    params: Iterable[torch.nn.Parameter],
    frames: Tensor,
    next_batch: BatchFn,
    cfg: FitConfig,
    seed: int,
    feed=None,
    label: str = "train",
    *,
    progress: ProgressSink,
    other_lrs: Sequence[tuple[Iterable[torch.nn.Parameter], float]] = (),
) -> list[list[float]]:
    """Train `params` with the backbone's own loss. Returns the loss curve [[step, loss], ...]
    (every `log_every` steps, plus the first and last). Raises NonFiniteLoss naming the step.
    `other_lrs`: (parameters, learning rate) trained at their own rate (a tuned encoder's, at
    Protocol.encoder_lr), under the same warm-up and decay; gradients are clipped over all."""
    optimizer, scheduler, params = make_optimizer(params, cfg, other_lrs)
    noise_gen = noise_generator(seed)
    bar = Progress(label, cfg.steps, progress)
    curve: list[list[float]] = []
    device = next(backbone.policy.parameters()).device
    for step, positions in enumerate(batch_order(len(frames), cfg, seed)):
        raw, features, noise, flow_time = draw_step(backbone, frames[positions], next_batch,
                                                    noise_gen)
        batch = backbone.preprocess(raw)
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
        clip_and_step(params, optimizer, scheduler, cfg)
        value = float(loss.detach())
        if step % cfg.log_every == 0 or step == cfg.steps - 1:
            curve.append([step, value])
        bar.update(step + 1, f"loss {value:.4f}")
    return curve
