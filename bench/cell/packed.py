"""Packed grafts: K projectors trained through ONE frozen-backbone pass a step.

The backbone is frozen and a sample never meets another in it (attention and norms act within a
sample), so K graft cells of one backbone can share its forward and backward: each cell draws its
step exactly as `bench.loops.train.fit` would alone (its own data order, flow noise and time
generators, its own batch function), the K batches are stacked into one, `PackedFeed` hands
slice k of every image batch to projector k, each cell's loss is the mean over its own samples,
and the SUM of the K losses is backpropagated: projector k only reaches loss k, so its gradient
is its own cell's. Clipping, AdamW and the schedule stay per cell. What differs from K runs of
`fit` is the float rounding of batched kernels only (tests/test_packed.py measures how much).

Not packable: cells that change the backbone (LoRA) or train their encoder (`other_lrs`).
`train_pack` trains grid cells so; `--pack-grafts K` (grid-file key `pack_grafts`) routes a
run's cells through it (bench.cell.pack_run).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from backbones.base import Backbone
from bench.progress import Progress, ProgressSink
from bench.loops.train import (
    BatchFn, FitConfig, NonFiniteLoss, batch_order, clip_and_step, draw_step, frozen_autocast,
    make_optimizer, noise_generator,
)


@dataclass
class PackedCell:
    """One graft cell of a pack: what `fit` takes for it alone (`cfg` None: the pack's)."""

    label: str
    params: Sequence[torch.nn.Parameter]
    feed: object  # a GraftFeed (graftcore.graft): bind / __call__ / assert_consumed
    frames: Tensor
    next_batch: BatchFn
    seed: int
    cfg: FitConfig | None = None


@dataclass
class PackedFit:
    """What training gave one cell: its loss curve as `fit` records it, or the NonFiniteLoss
    that stopped it (the other cells of the pack went on without it)."""

    label: str
    curve: list[list[float]] = field(default_factory=list)
    error: NonFiniteLoss | None = None


class PackedFeed:
    """Stands in for `embed_image` for K grafts at once: of each image batch the backbone hands
    over, the first sizes[0] samples go to feeds[0], the next sizes[1] to feeds[1], and so on;
    their projected tokens are concatenated back in the same order."""

    def __init__(self, feeds: Sequence, sizes: Sequence[int]) -> None:
        if len(feeds) != len(sizes):
            raise ValueError(f"{len(feeds)} feeds for {len(sizes)} slices")
        self.feeds, self.sizes = list(feeds), [int(s) for s in sizes]

    def __call__(self, image: Tensor) -> Tensor:
        if image.shape[0] != sum(self.sizes):
            raise RuntimeError(f"packed image batch {image.shape[0]} != the pack's "
                               f"{sum(self.sizes)} samples ({self.sizes})")
        parts = torch.split(image, self.sizes)
        return torch.cat([feed(part) for feed, part in zip(self.feeds, parts)])

    def assert_consumed(self) -> None:
        for feed in self.feeds:
            feed.assert_consumed()


def stack_raw(raws: Sequence[dict]) -> dict:
    """The raw batches of the pack's cells as one (backbones/base.py's raw batch): tensors
    concatenated along the batch, the task lists joined, in cell order."""
    keys = set(raws[0])
    for raw in raws[1:]:
        if set(raw) != keys:
            raise ValueError(f"packed cells' raw batches differ in keys: {sorted(keys ^ set(raw))}")
    return {k: (torch.cat([r[k] for r in raws]) if isinstance(raws[0][k], Tensor)
                else [x for r in raws for x in r[k]]) for k in raws[0]}


class _Run:
    """One cell's training state inside the pack: the same objects `fit` builds for it."""

    def __init__(self, cell: PackedCell, cfg: FitConfig) -> None:
        self.cell, self.cfg = cell, cfg
        self.optimizer, self.scheduler, self.params = make_optimizer(cell.params, cfg)
        self.noise_gen = noise_generator(cell.seed)
        self.order = batch_order(len(cell.frames), cfg, cell.seed)  # one draw per step trained
        self.result = PackedFit(cell.label)

    def trains_at(self, step: int) -> bool:
        return self.result.error is None and step < self.cfg.steps


def fit_packed(backbone: Backbone, cells: Sequence[PackedCell], cfg: FitConfig,
               label: str = "packed", *, progress: ProgressSink) -> list[PackedFit]:
    """Train the K cells' projectors together (see the module's docstring); one PackedFit per
    cell, in order. A cell whose loss turns non-finite stops there with a NonFiniteLoss naming
    it and the step; the others go on. Cells may have their own step counts (`cell.cfg`): a
    cell leaves the pack when its schedule ends."""
    if not cells:
        return []
    runs = [_Run(cell, cell.cfg or cfg) for cell in cells]
    total = max(run.cfg.steps for run in runs)
    bar = Progress(f"{label} ({len(runs)} packed grafts)", total, progress)
    device = next(backbone.policy.parameters()).device
    for step in range(total):
        active = [run for run in runs if run.trains_at(step)]
        if not active:
            break
        losses = _packed_losses(backbone, active, step, device)
        finite = []
        for run, loss in zip(active, losses):
            if torch.isfinite(loss):
                finite.append((run, loss))
            else:
                run.result.error = NonFiniteLoss(
                    f"{run.cell.label}: loss is {loss.item()} at step {step} of {run.cfg.steps} "
                    f"(packed with {len(runs) - 1} other graft(s)); lower the learning rate or "
                    "check the inputs/normalisation stats for NaN/inf")
        if not finite:
            continue
        for run, _ in finite:
            run.optimizer.zero_grad(set_to_none=True)
        torch.stack([loss for _, loss in finite]).sum().backward()
        for run, loss in finite:
            clip_and_step(run.params, run.optimizer, run.scheduler, run.cfg)
            value = float(loss.detach())
            if step % run.cfg.log_every == 0 or step == run.cfg.steps - 1:
                run.result.curve.append([step, value])
        bar.update(step + 1, "loss " + " ".join(f"{float(l.detach()):.4f}" for _, l in finite))
    return [run.result for run in runs]


def _packed_losses(backbone: Backbone, active: list[_Run], step: int,
                   device: torch.device) -> list[Tensor]:
    """Each active cell's mean loss of `step`, from one backbone pass over their stacked draws."""
    draws = [draw_step(backbone, run.cell.frames[next(run.order)], run.cell.next_batch,
                       run.noise_gen) for run in active]
    sizes = [len(noise) for _, _, noise, _ in draws]
    for run, (_, features, _, _) in zip(active, draws):
        if features is not None:
            run.cell.feed.bind(features)
    batch = backbone.preprocess(stack_raw([raw for raw, _, _, _ in draws]))
    noise = torch.cat([n for _, _, n, _ in draws])
    flow_time = torch.cat([t for _, _, _, t in draws])
    feed = PackedFeed([run.cell.feed for run in active], sizes)
    with backbone.image_embedder(feed), frozen_autocast(device):
        per_sample = backbone.loss(batch, noise, flow_time)
    feed.assert_consumed()
    return [part.mean() for part in torch.split(per_sample, sizes)]


# --- graft cells of the grid, packed ------------------------------------------------------------
@dataclass
class PackedGraft:
    """One graft cell trained in a pack: its graft (projector trained, in eval mode) and what its
    training gave (runner.Fitted, as runner.train_graft gives it alone), or the error; `timings`
    (seconds): its build and features, and as train its probe losses plus its 1/K share of the
    pack's training (the shares of a pack sum to its wall time)."""

    cell: object  # bench.grid.cells.CellSpec
    graft: object  # bench.cell.runner.Graft
    fitted: object = None  # bench.cell.runner.Fitted
    error: Exception | None = None
    timings: dict = field(default_factory=dict)


def packable(cell) -> str | None:
    """Why a cell cannot be trained in a pack (None: it can): it must train a projector of its
    own through the frozen policy, its encoder frozen."""
    kind = cell.spec
    if not cell.trains_projector:
        return "it trains no projector"
    if kind.lora:
        return "LoRA changes the backbone the pack shares"
    if kind.tune_encoder:
        return "its encoder trains (at its own learning rate)"
    if kind.live_encoder:
        return "its encoder runs in the loop (the pack reads stored features)"
    return None


def train_pack(cells: Sequence, ws, contexts: Sequence, label: str = "packed") -> list[PackedGraft]:
    """Build the graft cells of one backbone x suite as bench.cell.runner.measure builds them and
    train their projectors in one pack, each with what runner.train_graft does alone around its
    `fit` (its step count, probe loss before and after). Contexts: the cells' CellContexts (a
    reused projector is not packed: take it as runner.measure does)."""
    from bench.cell.runner import (Fitted, build_graft, cell_inputs, graft_fit_config,
                                  probe_frames, probe_loss)

    worlds = {(c.backbone, c.suite, c.release) for c in cells}
    reasons = [f"{c.id}: {why}" for c in cells if (why := packable(c))]
    reasons += [f"{c.id}: it takes its graft's projector" for c, x in zip(cells, contexts)
                if x.reuse is not None]
    if len(worlds) > 1 or reasons:
        raise ValueError(f"cannot pack {[c.id for c in cells]}: "
                         + ("; ".join(reasons) or f"{len(worlds)} backbone x suite pairs"))
    p = ws.profile.protocol
    cell0 = cells[0]
    lent = ws.lend(cell0.backbone, cell0.suite, cell0.release)
    backbone, split = lent.backbone, lent.split
    device, probe = next(backbone.policy.parameters()).device, probe_frames(split.train_frames)
    packed, members = [], []
    for cell, context in zip(cells, contexts):
        t0 = time.perf_counter()
        inputs = cell_inputs(cell, p, lent.suite, split, backbone, device)
        t1 = time.perf_counter()
        graft = build_graft(cell, ws, backbone, inputs, context)
        t2 = time.perf_counter()
        next_batch = inputs.train_batches(cell.spec.train_rule(cell.variant))
        cfg = graft_fit_config(cell, p)  # runner.train_graft's own schedule
        before = probe_loss(backbone, graft.feed, next_batch, probe, p.split_seed)
        timings = {"build": t1 - t0, "features": t2 - t1, "train": time.perf_counter() - t2}
        packed.append((PackedGraft(cell, graft, timings=timings), next_batch, before, cfg))
        members.append(PackedCell(cell.id, list(graft.projector.parameters()), graft.feed,
                                  split.train_frames, next_batch, cell.train_seed, cfg))
    t0 = time.perf_counter()
    fits = fit_packed(backbone, members, members[0].cfg, label=label, progress=ws.progress)
    share = (time.perf_counter() - t0) / len(members)
    for (item, next_batch, before, cfg), fitted in zip(packed, fits):
        item.timings["train"] += share
        if fitted.error is not None:
            item.error = fitted.error
            continue
        t0 = time.perf_counter()
        after = probe_loss(backbone, item.graft.feed, next_batch, probe, p.split_seed)
        item.timings["train"] += time.perf_counter() - t0
        item.graft.projector.eval()
        item.fitted = Fitted(fitted.curve, {"before": before, "after": after}, steps=cfg.steps)
    return [item for item, _, _, _ in packed]
