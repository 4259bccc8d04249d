"""One REAL-size SmolVLA cell, random init (no download): the per-step figures the paper-grid
arithmetic of docs/SCALING.md needs. Runs on CUDA; skipped on CPU unless
GRAFTBENCH_REALSIZE_CPU=1 (a smoke run at batch 2: minutes per step, not a measurement).

    .venv/bin/pytest benchmarks/bench_realsize.py --benchmark-only -p no:randomly

SmolVLA-450M's architecture (SmolVLM2-500M numbers, 16 of 32 text layers, 512 px, chunk 50)
from backbones.tiny_smolvla.real_shape_vlm_folder(), trained and scored on the tiny spatial
suite's frames (upsampled by the policy's own resize): the cost per step depends on the shapes,
not on the pixels. The paper protocol's batch (32) and eval batch (16) on CUDA.
"""

from __future__ import annotations

import os

from bench.progress import QUIET
import pytest
import torch

from bench.loops.evaluate import score
from graftcore.graft import GraftFeed, Projector
from bench.grid.protocol import PAPER, TINY, with_overrides
from bench.results.store import ResultStore
from bench.suites.windows import raw_batch
from bench.loops.train import FitConfig, fit, frozen_autocast
from bench.resources.workspace import Workspace

CUDA = torch.cuda.is_available()
pytestmark = pytest.mark.skipif(
    not CUDA and os.environ.get("GRAFTBENCH_REALSIZE_CPU") != "1",
    reason="real-size SmolVLA: needs CUDA (or GRAFTBENCH_REALSIZE_CPU=1 for a smoke run)")
DEVICE = torch.device("cuda" if CUDA else "cpu")
BATCH = PAPER.protocol.batch_size if CUDA else 2
STEPS = 5 if CUDA else 1
ROUNDS, WARMUP = (3, 1) if CUDA else (1, 0)  # CPU: a smoke run, not a measurement


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    """(workspace, real-size random-init SmolVLA backbone on DEVICE, suite, split)."""
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from bench.resources.releases import union_stats
    from backbones.smolvla import SmolVLABackbone
    from backbones.tiny_smolvla import libero_smolvla_config, real_shape_vlm_folder

    profile = with_overrides(TINY, backbones=("smolvla",), suites=("spatial",))
    ws = Workspace(profile, ResultStore(tmp_path_factory.mktemp("results")), progress=QUIET)
    suite, split = ws.suite("spatial"), ws.split("spatial")
    config = libero_smolvla_config(suite.camera_keys, suite.image_shape, 8, 7,
                                   vlm_model_name=str(real_shape_vlm_folder()),
                                   device=DEVICE.type, num_vlm_layers=16)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        policy = SmolVLAPolicy(config).to(DEVICE)
    stats = union_stats([suite], {suite.name: split.train_frames})
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    backbone = SmolVLABackbone(policy, pre, post)
    backbone.freeze()
    return ws, backbone, suite, split


def _features(ws, backbone):
    feats = ws.features("pixels", "spatial", backbone.info.native_grid)
    return feats, int(next(iter(feats.values())).shape[-1])


def _cfg(steps: int) -> FitConfig:
    p = PAPER.protocol
    return FitConfig(steps, BATCH, p.lr, p.weight_decay, 1, p.grad_clip, p.loss_log_every)


def _peak_mb() -> float:
    return torch.cuda.max_memory_allocated(DEVICE) / 2**20 if CUDA else float("nan")


def test_realsize_step_cached(real, benchmark, record_cost):
    ws, backbone, suite, split = real
    feats, channels = _features(ws, backbone)

    def next_batch(frames):
        raw = raw_batch(suite, frames, backbone.info.chunk_size, with_images=False)
        for k in suite.camera_keys:
            raw.setdefault(k, torch.zeros((len(frames), *suite.image_shape)))
        picked = {k: v[frames] for k, v in feats.items()}
        if CUDA:
            picked = {k: v.pin_memory().to(DEVICE, non_blocking=True) for k, v in picked.items()}
        return raw, picked

    def train():
        projector = Projector(channels, backbone.info.lm_width).to(DEVICE)
        feed = GraftFeed(projector, backbone.camera_keys, backbone.info.native_grid)
        fit(backbone, list(projector.parameters()), split.train_frames, next_batch, _cfg(STEPS),
            seed=0, feed=feed, progress=QUIET)
        if CUDA:
            torch.cuda.synchronize()

    if CUDA:
        torch.cuda.reset_peak_memory_stats(DEVICE)
    benchmark.pedantic(train, rounds=ROUNDS, warmup_rounds=WARMUP, iterations=1)
    benchmark.extra_info["peak_cuda_mb"] = _peak_mb()
    record_cost("realsize_step_cached/smolvla", steps=STEPS)


def test_realsize_floor(real, benchmark, record_cost):
    ws, backbone, suite, split = real
    info = backbone.info
    frames = split.train_frames[:BATCH]
    raw = raw_batch(suite, frames, info.chunk_size, with_images=False)
    for k in suite.camera_keys:
        raw[k] = torch.zeros((len(frames), *suite.image_shape))
    batch = backbone.preprocess(raw)
    gen = torch.Generator().manual_seed(0)
    noise = torch.randn((BATCH, info.chunk_size, info.max_action_dim), generator=gen).to(DEVICE)
    flow_time = backbone.sample_time(BATCH, gen)
    tokens = info.native_grid[0] * info.native_grid[1]
    fixed = torch.randn((BATCH, tokens, info.lm_width), device=DEVICE, requires_grad=True)

    def forward_backward():
        for _ in range(STEPS):
            with backbone.image_embedder(lambda image: fixed), frozen_autocast(DEVICE):
                loss = backbone.loss(batch, noise, flow_time).mean()
            loss.backward()
            fixed.grad = None
        if CUDA:
            torch.cuda.synchronize()

    benchmark.pedantic(forward_backward, rounds=ROUNDS, warmup_rounds=WARMUP, iterations=1)
    record_cost("realsize_floor/smolvla", steps=STEPS)


def test_realsize_eval(real, benchmark, record_cost):
    ws, backbone, suite, split = real
    feats, channels = _features(ws, backbone)
    torch.manual_seed(0)
    feed = GraftFeed(Projector(channels, backbone.info.lm_width).to(DEVICE), backbone.camera_keys,
                     backbone.info.native_grid)
    windows = split.windows if CUDA else split.windows[:2]
    eval_batch = PAPER.protocol.eval_batch_size if CUDA else 2

    def run():
        score(backbone, suite, windows, eval_batch, PAPER.protocol.eval_noise_seed, feed=feed,
              features_for=lambda pos, frames: {k: v[frames] for k, v in feats.items()})

    benchmark.pedantic(run, rounds=ROUNDS, warmup_rounds=0, iterations=1)
    record_cost("realsize_eval_batched/smolvla", windows=len(windows))
