"""One cell, top to bottom: build graft -> train projector -> score -> record."""

from __future__ import annotations

import datetime as dt
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from bench import cells as K
from bench.cells import CellSpec
from bench.evaluate import derangement, score
from bench.features import encode_pooled
from bench.graft import GraftFeed, Projector, assert_only_trainable, trainable_parameters
from bench.provenance import (
    git_commit, hardware, peak_memory_mb, reset_peak_memory, stable_seed, versions,
)
from backbones.released import checkpoint_id
from bench.closed_loop import cell_rollouts
from bench.suites.windows import raw_batch
from bench.train import FitConfig, fit, frozen_autocast
from bench.workspace import Workspace

SCHEMA = 1


class _Captured(Exception):
    def __init__(self, image):
        self.image = image


def pooling_grid(native: tuple[int, int], variant: str | None) -> tuple[int, int]:
    """The token grid per camera of a cell: native, or the pooling control's variant."""
    rows, cols = native
    return {
        None: native,
        "half": (max(1, rows // 2), max(1, cols // 2)),
        "double": (rows * 2, cols * 2),
        "global": (1, 1),
    }[variant]


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


@dataclass(frozen=True)
class TrainedProjector:
    """A trained projector kept for the session (its weights on disk: a paper grid trains hundreds
    of projectors of up to ~10 MB each), with what its training recorded."""

    path: Path
    curve: list
    probe_losses: dict
    cell_id: str


def shared_projector_key(cell: CellSpec, features_mode: str) -> tuple | None:
    """Key of the projector a cell trains when its graft trains exactly the same one: the graft
    itself, its shuffled_image control and its zero_image[eval] control (same seed, data, grid;
    only evaluation differs). None for every other cell."""
    same_training = cell.kind == K.GRAFT or (cell.encoder is not None and (
        cell.kind == K.SHUFFLED_IMAGE or (cell.kind == K.ZERO_IMAGE and cell.variant == "eval")))
    if not same_training or features_mode != "cache":
        return None
    graft = cell if cell.kind == K.GRAFT else cell.reference
    return (graft.id, features_mode)


def run_cell(cell: CellSpec, ws: Workspace, features_mode: str = "cache") -> dict:
    """Measure one cell and write its record. features_mode: "cache" (pooled features computed
    once per frame) or "loop" (the encoder runs inside every step: the naive reference)."""
    if features_mode not in ("cache", "loop"):
        raise ValueError(f"features_mode {features_mode!r} not in ('cache', 'loop')")
    p = ws.profile.protocol
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    suite = ws.suite(cell.suite)
    split = ws.split(cell.suite)
    backbone = (ws.fresh_backbone(cell.backbone, cell.suite) if cell.kind == K.LORA
                else ws.backbone(cell.backbone, cell.suite))
    info = backbone.info
    device = next(backbone.policy.parameters()).device
    reset_peak_memory(device)
    grid = pooling_grid(info.native_grid, cell.variant if cell.kind == K.POOLING else None)
    perm = derangement(len(split.windows), p.split_seed)

    feed = projector = projector_from = None
    encoder = None
    curve: list[list[float]] = []
    lora_params = 0
    timings["build"] = time.perf_counter() - t_start

    if cell.trains_projector:
        t0 = time.perf_counter()
        if cell.kind == K.NATIVE_WRAPPED:
            channels = native_tower_channels(backbone, suite, split.train_frames)
            tower = backbone.native_tower_grid
            features = None
        else:
            encoder = ws.encoder(cell.encoder)
            tower = None
            features = ws.features(cell.encoder, cell.suite, grid) if features_mode == "cache" else None
            channels = int(next(iter(features.values())).shape[-1]) if features else encoder.channels
        timings["features"] = time.perf_counter() - t0

        def pooled(frames, source_frames=None):
            """Graft features of `frames` (from `source_frames`' pixels for shuffled images)."""
            src = frames if source_frames is None else source_frames
            if features is not None:
                picked = {k: v[src] for k, v in features.items()}
                if device.type == "cuda":  # pinned host memory: the copy overlaps the compute
                    picked = {k: v.pin_memory().to(device, non_blocking=True) for k, v in picked.items()}
                return picked
            return encode_pooled(encoder, suite.images(src), grid)

        def zero_pooled(n):
            blank = {k: torch.zeros((1, *suite.image_shape)) for k in suite.camera_keys}
            return {k: v.expand(n, -1, -1) for k, v in encode_pooled(encoder, blank, grid).items()}

        with torch.random.fork_rng():
            torch.manual_seed(stable_seed(cell.seed, "projector-init"))
            projector = Projector(channels, info.lm_width).to(device)
        if cell.kind == K.LORA:
            with torch.random.fork_rng():  # peft draws lora_A's init from the global generator
                torch.manual_seed(stable_seed(cell.seed, "lora-init"))
                lora_params = _add_lora(backbone, p)
        expected = trainable_parameters(projector) + lora_params
        frozen = [backbone.policy] + ([encoder] if encoder is not None else [])
        assert_only_trainable(expected, projector, *frozen,
                              what="projector + LoRA" if lora_params else "projector")
        feed = GraftFeed(projector, backbone.camera_keys, grid, tower=tower)
        train_zero = cell.kind == K.ZERO_IMAGE and cell.variant == "train"
        needs_pixels = tower is not None or features is None

        def next_batch(frames):
            raw = raw_batch(suite, frames, info.chunk_size, with_images=needs_pixels)
            for k in suite.camera_keys:  # the graft ignores them; the policy's pipeline wants them
                raw.setdefault(k, torch.zeros((len(frames), *suite.image_shape)))
            if tower is not None:
                return raw, None
            return raw, zero_pooled(len(frames)) if train_zero else pooled(frames)

        # A test or --degrade-encoder transform changes the features: never share across it.
        share = (shared_projector_key(cell, features_mode)
                 if cell.encoder not in ws.feature_transforms else None)
        trained = ws.trained_projectors.get(share) if cell.kind != K.GRAFT else None
        t0 = time.perf_counter()
        if trained is not None:
            # The same seed, data and code train the identical projector: take the graft's.
            projector.load_state_dict(load_file(trained.path, device=str(device)))
            curve, probe_losses, projector_from = trained.curve, trained.probe_losses, trained.cell_id
        else:
            probe = probe_frames(split.train_frames)
            probe_before = probe_loss(backbone, feed, next_batch, probe, p.split_seed)
            params = list(projector.parameters()) + [
                q for q in backbone.policy.parameters() if q.requires_grad
            ]
            fit_cfg = FitConfig(p.steps, p.batch_size, p.lr, p.weight_decay, p.warmup_steps,
                                p.grad_clip, p.loss_log_every)
            curve = fit(backbone, params, split.train_frames, next_batch, fit_cfg, cell.seed,
                        feed=feed, label=cell.id, progress=ws.progress)
            probe_losses = {"before": probe_before,
                            "after": probe_loss(backbone, feed, next_batch, probe, p.split_seed)}
            if share is not None:
                path = ws.session_dir() / f"projector-{cell.id}.safetensors"
                save_file({k: v.detach().cpu().contiguous() for k, v in projector.state_dict().items()},
                          path)
                ws.trained_projectors[share] = TrainedProjector(path, curve, probe_losses, cell.id)
        timings["train"] = time.perf_counter() - t0
        projector.eval()

        if tower is not None:
            features_for = None
        elif cell.kind == K.ZERO_IMAGE:
            features_for = lambda pos, frames: zero_pooled(len(frames))  # noqa: E731
        elif cell.kind == K.SHUFFLED_IMAGE:
            features_for = lambda pos, frames: pooled(frames, split.windows[perm[pos]])  # noqa: E731
        else:
            features_for = lambda pos, frames: pooled(frames)  # noqa: E731
        images_for = None
    else:
        timings["features"] = timings["train"] = 0.0
        probe_losses = None
        features_for = None
        if cell.kind == K.ZERO_IMAGE:
            images_for = lambda pos, frames, imgs: {k: torch.zeros_like(v) for k, v in imgs.items()}  # noqa: E731
        elif cell.kind == K.SHUFFLED_IMAGE:
            images_for = lambda pos, frames, imgs: suite.images(split.windows[perm[pos]])  # noqa: E731
        else:
            images_for = None

    t0 = time.perf_counter()
    scores = score(backbone, suite, split.windows, p.eval_batch_size, p.eval_noise_seed,
                   feed=feed, features_for=features_for, images_for=images_for)
    timings["eval"] = time.perf_counter() - t0
    rollouts = None
    if ws.rollouts:
        t0 = time.perf_counter()
        rollouts = cell_rollouts(cell, suite, backbone, ws.rollouts, feed=feed, encoder=encoder,
                                 grid=grid, progress=ws.progress)
        timings["rollouts"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start

    ref = cell.reference
    record = {
        "schema": SCHEMA, "status": "ok", "cell_id": cell.id, "kind": cell.kind,
        "backbone": cell.backbone, "suite": cell.suite, "encoder": cell.encoder,
        "seed": cell.seed, "variant": cell.variant, "reference": ref.id if ref else None,
        "grid": list(grid), "features_mode": features_mode if encoder is not None else None,
        "profile": ws.profile.name, "protocol": p.to_dict(), "protocol_hash": p.hash,
        "checkpoint": {**checkpoint_id(cell.backbone, ws.profile),
                       "normalizer": ws.normalizer(cell.backbone, cell.suite).source,
                       "normalizer_fingerprint": backbone.normalizer_fingerprint()},
        **scores,
        "trainable_params": trainable_parameters(projector, backbone.policy) if projector else 0,
        "projector_params": trainable_parameters(projector) if projector else 0,
        "lora_params": lora_params,
        "projector_from": projector_from,
        "loss_curve": curve,
        "probe_loss": probe_losses,
        "encoder_weights": getattr(encoder, "weights_id", None),
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "peak_memory_mb": peak_memory_mb(device), "device": str(device), "hardware": hardware(),
        "versions": versions(), "git_commit": git_commit(),
        "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
    }
    if rollouts is not None:
        record["rollouts"] = rollouts
    ws.store.write(record)
    return record


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
