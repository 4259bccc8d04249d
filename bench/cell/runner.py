"""One cell, top to bottom: build the graft -> train its projector -> score -> its record,
returned (bench.cell.service writes it, with the projector file, and keeps the projector a later
cell takes).

What a kind of cell does differently is read from its entry in bench.grid.kinds; no branch here
names a kind."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from safetensors.torch import load_file

from bench.grid.cells import CellSpec
from bench.loops.evaluate import derangement, score
from bench.resources.features import feature_runtime
from bench.cell.freeze import assert_only_trainable, trainable_parameters, tunable_copy
from graftcore.graft import GraftFeed, Projector
from bench.cell.inputs import CellInputs
from bench.cell.plan import CellContext, CellResult
from bench.results.provenance import (
    git_commit, hardware, peak_memory_mb, reset_peak_memory, stable_seed, versions,
)
from bench.cell.rollouts import (LoopGraft, cell_rollouts, policy_fingerprint,
                                 policy_identity)
from bench.results.record import (
    MeasuredUnder, RunInfo, Training as TrainingPart, checkpoint_of, new_record,
)
from bench.suites.windows import raw_batch
from bench.loops.train import FitConfig, fit, frozen_autocast
from bench.resources.workspace import Lent, Workspace


class _Captured(Exception):
    def __init__(self, image):
        self.image = image


def native_tower_channels(backbone, suite, frames) -> int:
    """Channels of the native tower's grid, probed on the image the policy hands its tower."""
    def capture(image):
        raise _Captured(image)

    batch = backbone.preprocess(raw_batch(suite, frames[:1], backbone.info.chunk_size))
    noise = torch.zeros((1, backbone.info.chunk_size, backbone.info.max_action_dim))
    try:
        with backbone.image_embedder(capture), torch.no_grad():
            backbone.loss(batch, noise, torch.full((1,), 0.5))
    except _Captured as c:
        return int(backbone.native_tower_grid(c.image).shape[1])
    raise RuntimeError("the backbone never called its image embedder")


def probe_frames(train_frames: torch.Tensor, n: int = 64) -> torch.Tensor:
    """A fixed spread of training frames on which the loss is measured before and after."""
    return train_frames[:: max(1, len(train_frames) // n)][:n]


@torch.no_grad()
def probe_loss(backbone, feed, next_batch, frames: torch.Tensor, seed: int) -> float:
    """Mean flow-matching loss on `frames` with fixed noise and time: unlike the noisy training
    curve, comparable before and after training (did the projector learn anything?)."""
    info = backbone.info
    gen = torch.Generator().manual_seed(stable_seed(seed, "probe-loss"))
    noise = torch.randn((len(frames), info.chunk_size, info.max_action_dim), generator=gen)
    flow_time = backbone.sample_time(len(frames), gen)
    raw, features = next_batch(frames)
    if features is not None:
        feed.bind(features)
    device = next(backbone.policy.parameters()).device
    with backbone.image_embedder(feed), frozen_autocast(device):  # as in training
        loss = backbone.loss(backbone.preprocess(raw), noise, flow_time).mean()
    feed.assert_consumed()
    return float(loss)


@dataclass
class Graft:
    """What a training cell splices in: the projector, its feed, and what it trains with."""

    projector: Projector
    feed: GraftFeed
    inputs: CellInputs
    lora_params: int = 0
    encoder_params: int = 0  # the tuned encoder's weights (tune_encoder kinds), trained too


@dataclass
class Fitted:
    """What training the projector gave (the record's Training part is built from it)."""

    curve: list
    probe_losses: dict | None = None
    projector_from: str | None = None  # the graft cell whose trained projector this cell took
    steps: int | None = None  # optimiser steps the projector took (its graft's, when taken)


def measure(cell: CellSpec, ws: Workspace, context: CellContext) -> CellResult:
    """One cell, top to bottom, with the context its plan gave: build the graft -> train its
    projector (or take its graft's) -> score -> the record and the trained projector, returned
    for the service to write and keep."""
    p, kind = ws.profile.protocol, cell.spec
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    lent = ws.lend(cell.backbone, cell.suite, cell.release, fresh=kind.lora)
    backbone = lent.backbone
    device = next(backbone.policy.parameters()).device
    reset_peak_memory(device)
    inputs = cell_inputs(cell, p, lent.suite, lent.split, backbone, device)
    timings["build"] = time.perf_counter() - t_start

    graft, training = None, Fitted(curve=[])
    if cell.trains_projector:
        t0 = time.perf_counter()
        graft = build_graft(cell, ws, backbone, inputs, context)
        timings["features"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        training = train_graft(cell, ws, backbone, graft, context)
        timings["train"] = time.perf_counter() - t0
    else:
        timings["features"] = timings["train"] = 0.0
    return score_cell(cell, ws, context, lent, inputs, graft, training, timings,
                      spent=time.perf_counter() - t_start)


def score_cell(cell: CellSpec, ws: Workspace, context: CellContext, lent: Lent,
               inputs: CellInputs, graft: Graft | None, training: Fitted,
               timings: dict[str, float], spent: float) -> CellResult:
    """The cell's trained graft (or none) scored on the held-out windows, rolled out when the run
    asks: its record (no projector file yet: the service writes both) and the trained projector.
    `timings`: the phases so far (seconds); `spent`: the seconds they took in all (a packed
    cell: its share of the pack, bench.cell.pack_run). `lent`: what the workspace lent the cell;
    `ws` is read for the run's settings only (protocol, rollouts, store, progress)."""
    p, kind = ws.profile.protocol, cell.spec
    suite, split, backbone = lent.suite, lent.split, lent.backbone
    device = next(backbone.policy.parameters()).device
    t_scoring = t0 = time.perf_counter()
    scores = score(backbone, suite, split.windows, p.eval_batch_size, p.eval_noise_seed,
                   feed=graft.feed if graft else None,
                   features_for=inputs.eval_features(kind.eval_inputs),
                   images_for=inputs.eval_images(kind.eval_inputs))
    timings["eval"] = time.perf_counter() - t0
    measured = measured_under(cell, ws, lent, inputs, context)
    rollouts = None
    if ws.rollouts:
        t0 = time.perf_counter()
        feed = graft.feed if graft else None
        rollouts = cell_rollouts(
            cell, suite, backbone, ws.rollouts, store=ws.store, progress=ws.progress,
            graft=LoopGraft(feed, inputs.encoder, inputs.grid) if graft else None,
            batching=ws.rollout_batching,
            policy=policy_fingerprint(backbone, feed, policy_identity(measured)))
        timings.update(rollouts=time.perf_counter() - t0)  # the phase (a timings_s entry)
    timings["total"] = spent + time.perf_counter() - t_scoring

    record = new_record(
        cell,
        measured=measured,
        scores=scores,
        training=training_fields(backbone, graft, training, inputs.encoder),
        run=RunInfo(timings_s={k: round(v, 3) for k, v in timings.items()},
                    peak_memory_mb=peak_memory_mb(device), device=str(device),
                    hardware=hardware(), versions=versions(), git_commit=git_commit(),
                    rollouts=rollouts))
    return CellResult(record, projector=graft.projector if graft else None)


def cell_inputs(cell: CellSpec, p, suite, split, backbone, device) -> CellInputs:
    """What the cell feeds its graft or policy (bench.cell.inputs), under the protocol `p`."""
    return CellInputs(suite, split.windows, derangement(len(split.windows), p.split_seed),
                      backbone.info.chunk_size, device,
                      cell.spec.grid(backbone.info.native_grid, cell.variant),
                      tower=cell.spec.tower, train_shift=p.graft_image_shift,
                      shift_seed=stable_seed(cell.train_seed, "graft-image-shift"),
                      tune_encoder=cell.spec.tune_encoder, train_frames=split.train_frames)


def build_graft(cell: CellSpec, ws: Workspace, backbone, inputs: CellInputs,
                context: CellContext) -> Graft:
    """The projector (seeded init), LoRA or a tuned copy of the encoder when the kind asks for
    it, the feed; frozen by construction and checked: only the projector (+ LoRA or encoder)
    trains."""
    p, info = ws.profile.protocol, backbone.info
    if inputs.tower:
        channels = native_tower_channels(backbone, inputs.suite, inputs.train_frames)
    else:
        inputs.encoder = ws.encoder(cell.encoder)
        if cell.spec.tune_encoder:  # its own copy, in the loop (stored features: the frozen one)
            inputs.encoder = tunable_copy(inputs.encoder, cell.encoder)
        elif cell.spec.live_encoder:
            pass  # the session's frozen encoder, in the loop: the stored features are skipped
        elif context.features_mode == "cache":
            inputs.features = ws.features(cell.encoder, cell.suite, inputs.grid,
                                          transform=context.feature_transform)
        channels = (int(next(iter(inputs.features.values())).shape[-1]) if inputs.features
                    else inputs.encoder.channels)
    with torch.random.fork_rng():
        torch.manual_seed(stable_seed(cell.train_seed, "projector-init"))
        projector = Projector(channels, info.lm_width).to(inputs.device)
    lora_params = 0
    if cell.spec.lora:
        with torch.random.fork_rng():  # peft draws lora_A's init from the global generator
            torch.manual_seed(stable_seed(cell.train_seed, "lora-init"))
            lora_params = _add_lora(backbone, p)
    encoder_params = trainable_parameters(inputs.encoder) if cell.spec.tune_encoder else 0
    frozen = [backbone.policy] + ([inputs.encoder] if inputs.encoder is not None else [])
    what = " + ".join(["projector"] + ["LoRA"] * bool(lora_params)
                      + ["encoder"] * bool(encoder_params))
    assert_only_trainable(trainable_parameters(projector) + lora_params + encoder_params,
                          projector, *frozen, what=what)
    feed = GraftFeed(projector, backbone.camera_keys, inputs.grid,
                     tower=backbone.native_tower_grid if inputs.tower else None)
    return Graft(projector, feed, inputs, lora_params, encoder_params)


def graft_fit_config(cell: CellSpec, p) -> FitConfig:
    """The projector's schedule for `cell` under protocol `p`: a short graft (bench.grid.kinds
    train_fraction) runs the whole schedule, compressed."""
    steps, warmup = (cell.spec.scaled_steps(n, cell.variant) for n in (p.steps, p.warmup_steps))
    return FitConfig(steps, p.batch_size, p.lr, p.weight_decay, warmup, p.grad_clip,
                     p.loss_log_every)


def train_graft(cell: CellSpec, ws: Workspace, backbone, graft: Graft,
                context: CellContext) -> Fitted:
    """Fit the projector, or take the identical one its graft trained this session (the plan's
    `context.reuse`)."""
    p, train_frames = ws.profile.protocol, graft.inputs.train_frames
    device = graft.inputs.device
    next_batch = graft.inputs.train_batches(cell.spec.train_rule(cell.variant))
    reused = context.reuse
    if reused is not None:
        graft.projector.load_state_dict(load_file(reused.path, device=str(device)))
        graft.projector.eval()
        return Fitted(reused.curve, reused.probe_losses, reused.cell_id, p.steps)
    probe = probe_frames(train_frames)
    before = probe_loss(backbone, graft.feed, next_batch, probe, p.split_seed)
    params = list(graft.projector.parameters()) + [
        q for q in backbone.policy.parameters() if q.requires_grad]
    fit_cfg = graft_fit_config(cell, p)
    # A tuned encoder trains at its own, lower rate (Protocol.encoder_lr), same schedule.
    tuned = ([(graft.inputs.encoder.parameters(), p.encoder_lr)] if graft.encoder_params else [])
    curve = fit(backbone, params, train_frames, next_batch, fit_cfg, cell.train_seed,
                feed=graft.feed, label=cell.id, progress=ws.progress, other_lrs=tuned)
    probe_losses = {"before": before,
                    "after": probe_loss(backbone, graft.feed, next_batch, probe, p.split_seed)}
    graft.projector.eval()
    return Fitted(curve, probe_losses, steps=fit_cfg.steps)


def measured_under(cell: CellSpec, ws: Workspace, lent: Lent, inputs: CellInputs,
                   context: CellContext) -> MeasuredUnder:
    """What `cell` was measured under, from what the workspace lent it (`lent`) and the run's
    profile and feature dtype (`ws`)."""
    p, features_mode = ws.profile.protocol, context.features_mode
    transform = context.feature_transform if inputs.encoder is not None else None
    grid_file = ws.profile.grid_file  # absent without --grid: those records stay as they were
    camera_map, dataset = user_world_fields(cell, ws.profile, lent)
    return MeasuredUnder(
        profile=ws.profile.name, protocol=p.to_dict(), protocol_hash=p.hash,
        checkpoint=checkpoint_of(lent.checkpoint, lent.normalizer.source,
                                 lent.backbone.normalizer_fingerprint()),
        grid=list(inputs.grid),
        features_mode=features_mode if inputs.encoder is not None else None,
        feature_dtype=ws.feature_dtype if inputs.features is not None else None,
        feature_runtime=feature_runtime(inputs.features),
        # never resumed, never a baseline
        feature_transform=(getattr(transform, "description", "a feature transform")
                           if transform is not None else None),
        grid_file=grid_file.provenance() if grid_file is not None else None,
        camera_map=camera_map, dataset=dataset,
    )


def user_world_fields(cell: CellSpec, profile, lent: Lent) -> tuple[dict | None, dict | None]:
    """A --policy's camera pairing and a --dataset's identity (None for the registry's)."""
    camera_map = dataset = None
    backbone = lent.backbone
    if lent.user_policy:
        rename = getattr(backbone, "rename_map", {}) or {}
        camera_map = {rename.get(k, k): k for k in backbone.camera_keys}
    datasets = dict(profile.datasets)
    if cell.suite in datasets:
        suite = lent.suite
        dataset = {"source": datasets[cell.suite], "root": suite.root,
                   "repo_id": suite.repo_id, "fingerprint": suite.fingerprint,
                   "fps": suite.fps, "cameras": list(suite.camera_keys)}
    return camera_map, dataset


def training_fields(backbone, graft: Graft | None, training: Fitted, encoder) -> TrainingPart:
    """What trained (the projector's file and sha256 are the service's to add: it writes it)."""
    projector = graft.projector if graft else None
    # The encoder counts only when it trained (a tuned encoder); a frozen one adds 0.
    modules = [projector, backbone.policy] + ([encoder] if encoder is not None else [])
    return TrainingPart(
        trainable_params=trainable_parameters(*modules) if projector else 0,
        projector_params=trainable_parameters(projector) if projector else 0,
        lora_params=graft.lora_params if graft else 0,
        projector_from=training.projector_from,
        loss_curve=training.curve,
        probe_loss=training.probe_losses,
        encoder_weights=getattr(encoder, "weights_id", None),
        encoder_input_size=_input_size(encoder),
        train_steps=training.steps,
    )


def _input_size(encoder) -> int | None:
    """The side the encoder resizes its input to (timm, user and known encoders keep it)."""
    size = getattr(encoder, "input_size", None)
    return int(size) if size is not None else None


def _add_lora(backbone, p) -> int:
    """LoRA adapters (peft) on the frozen LM's attention; returns the adapter parameter count."""
    from peft import LoraConfig, inject_adapter_in_model

    lm = backbone.language_model()
    config = LoraConfig(r=p.lora_rank, lora_alpha=p.lora_alpha,
                        target_modules=list(p.lora_targets), lora_dropout=0.0, bias="none")
    inject_adapter_in_model(config, lm)
    adapters = [q for n, q in lm.named_parameters() if "lora_" in n]
    if not adapters:
        raise RuntimeError(
            f"LoRA targets {p.lora_targets} matched no module of the {backbone.info.name} LM"
        )
    for q in adapters:
        q.requires_grad_(True)
    return sum(q.numel() for q in adapters)
