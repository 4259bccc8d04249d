"""What one cell costs, phase by phase, on the tiny profile (the offline world).

- step_cached: one projector training step as the runner takes it (bench.loops.train.fit), pooled
  features gathered from the cache;
- step_naive_<encoder>: the same step with the encoder in the loop (pixels -> encoder -> pool);
- floor: the frozen backbone's own forward + backward on pre-projected inputs (the image
  embedder returns a fixed tensor that requires grad; batches prepared beforehand);
- features:<encoder>: feature extraction (image load + encoder + pooling) per frame;
- eval_*: offline scoring (bench.loops.evaluate.score) of the held-out windows, batched, and one
  window per sampler call for contrast.
"""

from __future__ import annotations

from dataclasses import dataclass

from bench.progress import QUIET
import pytest
import torch

from bench.loops.evaluate import score
from bench.loops.encode import encode_pooled
from graftcore.graft import GraftFeed, Projector
from bench.grid.protocol import TINY, with_overrides
from bench.results.store import ResultStore
from bench.suites.windows import raw_batch
from bench.loops.train import FitConfig, batch_order, fit
from bench.resources.workspace import Workspace

BACKBONES = ("pi05", "smolvla")
STEPS = 5  # training steps per timed call (fit's own set-up is amortised over them)
# Ratios from the minimum over rounds: on shared cores the min is the least disturbed estimate
# (medians carry whatever else the machine was doing).
ROUNDS = 10


@dataclass
class World:
    name: str
    ws: Workspace
    backbone: object
    suite: object
    train_frames: torch.Tensor
    windows: torch.Tensor

    @property
    def grid(self) -> tuple[int, int]:
        return self.backbone.info.native_grid


@pytest.fixture(scope="module", params=BACKBONES)
def world(request, tmp_path_factory) -> World:
    profile = with_overrides(TINY, backbones=(request.param,), suites=("spatial",))
    ws = Workspace(profile, ResultStore(tmp_path_factory.mktemp("results")), progress=QUIET)
    split = ws.split("spatial")
    return World(request.param, ws, ws.backbone(request.param), ws.suite("spatial"),
                 split.train_frames, split.windows)


def _fit_config(steps: int) -> FitConfig:
    p = TINY.protocol
    return FitConfig(steps, p.batch_size, p.lr, p.weight_decay, p.warmup_steps, p.grad_clip,
                     p.loss_log_every)


def _placeholders(world: World, raw: dict, n: int) -> dict:
    for k in world.suite.camera_keys:  # the graft ignores them; the policy's pipeline wants them
        raw.setdefault(k, torch.zeros((n, *world.suite.image_shape)))
    return raw


def _train_projector(world: World, channels: int, next_batch, steps: int = STEPS) -> None:
    """`steps` projector steps through bench.loops.train.fit, as bench.cell.service.run_cell
    runs them."""
    torch.manual_seed(0)
    projector = Projector(channels, world.backbone.info.lm_width)
    feed = GraftFeed(projector, world.backbone.camera_keys, world.grid)
    fit(world.backbone, list(projector.parameters()), world.train_frames, next_batch,
        _fit_config(steps), seed=0, feed=feed, progress=QUIET)


def _time(benchmark, fn, rounds: int = ROUNDS) -> None:
    benchmark.pedantic(fn, rounds=rounds, warmup_rounds=1, iterations=1)


def test_step_cached(world, benchmark, record_cost):
    features = world.ws.features("pixels", "spatial", world.grid)
    channels = int(next(iter(features.values())).shape[-1])

    def next_batch(frames):
        raw = raw_batch(world.suite, frames, world.backbone.info.chunk_size, with_images=False)
        return _placeholders(world, raw, len(frames)), {k: v[frames] for k, v in features.items()}

    _time(benchmark, lambda: _train_projector(world, channels, next_batch))
    record_cost(f"step_cached/{world.name}", steps=STEPS)


def test_floor(world, benchmark, record_cost):
    """Backbone forward + backward alone: prepared batches, fixed pre-projected image tokens."""
    bb, info = world.backbone, world.backbone.info
    cfg = _fit_config(STEPS)
    gen = torch.Generator().manual_seed(0)
    prepared = []
    for positions in batch_order(len(world.train_frames), cfg, seed=0):
        frames = world.train_frames[positions]
        raw = raw_batch(world.suite, frames, info.chunk_size, with_images=False)
        batch = bb.preprocess(_placeholders(world, raw, len(frames)))
        noise = torch.randn((len(frames), info.chunk_size, info.max_action_dim), generator=gen)
        prepared.append((batch, noise, bb.sample_time(len(frames), gen)))
    tokens = info.native_grid[0] * info.native_grid[1]
    fixed = torch.randn((cfg.batch_size, tokens, info.lm_width), requires_grad=True)

    def forward_backward():
        for batch, noise, flow_time in prepared:
            with bb.image_embedder(lambda image: fixed):
                loss = bb.loss(batch, noise, flow_time).mean()
            loss.backward()
            fixed.grad = None

    _time(benchmark, forward_backward)
    record_cost(f"floor/{world.name}", steps=STEPS)


def _naive_next_batch(world: World, encoder):
    def next_batch(frames):
        raw = raw_batch(world.suite, frames, world.backbone.info.chunk_size, with_images=False)
        pooled = encode_pooled(encoder, world.suite.images(frames), world.grid)
        return _placeholders(world, raw, len(frames)), pooled

    return next_batch


@pytest.mark.parametrize("encoder_name", ["siglip", "dinov2_s"])
def test_step_naive(world, encoder_name, benchmark, record_cost):
    encoder = world.ws.encoder(encoder_name)
    next_batch = _naive_next_batch(world, encoder)
    _time(benchmark, lambda: _train_projector(world, encoder.channels, next_batch))
    record_cost(f"step_naive_{encoder_name}/{world.name}", steps=STEPS)


@pytest.mark.parametrize("encoder_name", ["siglip", "dinov2_s", "fastvit", "repvit", "pixels"])
def test_feature_extraction(encoder_name, benchmark, record_cost, tmp_path_factory):
    """Image load + encoder + pooling to pi0.5's tiny grid, 32 frames (all cameras) per call."""
    profile = with_overrides(TINY, suites=("spatial",))
    ws = Workspace(profile, ResultStore(tmp_path_factory.mktemp("results")), progress=QUIET)
    suite, encoder = ws.suite("spatial"), ws.encoder(encoder_name)
    frames = torch.arange(32)
    _time(benchmark, lambda: encode_pooled(encoder, suite.images(frames), (4, 4)), rounds=7)
    record_cost(f"features:{encoder_name}", frames=len(frames))


@pytest.mark.parametrize("batch_size", [TINY.protocol.eval_batch_size, 1])
def test_eval_windows(world, batch_size, benchmark, record_cost):
    """All held-out windows of the suite through the backbone's own sampler; checks that the
    prefix (image tokens included) is embedded once per sampler call, not once per denoise step."""
    features = world.ws.features("pixels", "spatial", world.grid)
    channels = int(next(iter(features.values())).shape[-1])
    torch.manual_seed(0)
    feed = GraftFeed(Projector(channels, world.backbone.info.lm_width), world.backbone.camera_keys,
                     world.grid)
    calls = {"embed": 0}
    counting = _CountingFeed(feed, calls)
    p = TINY.protocol

    def features_for(positions, frames):
        return {k: v[frames] for k, v in features.items()}

    def run():
        score(world.backbone, world.suite, world.windows, batch_size, p.eval_noise_seed,
              feed=counting, features_for=features_for)

    calls["embed"] = 0
    run()
    sampler_calls = -(-len(world.windows) // batch_size)
    assert calls["embed"] == sampler_calls * len(world.backbone.camera_keys), (
        f"{calls['embed']} image embeddings for {sampler_calls} sampler calls: the prefix is "
        "rebuilt inside the denoising loop")
    _time(benchmark, run, rounds=3 if batch_size == 1 else 7)
    kind = "eval_batched" if batch_size > 1 else "eval_one_window_per_call"
    record_cost(f"{kind}/{world.name}", windows=len(world.windows))


class _CountingFeed:
    """A GraftFeed that counts embed_image calls (the adapters call the feed object itself)."""

    def __init__(self, feed: GraftFeed, calls: dict) -> None:
        self.feed, self.calls = feed, calls

    def bind(self, features) -> None:
        self.feed.bind(features)

    def assert_consumed(self) -> None:
        self.feed.assert_consumed()

    def __call__(self, image):
        self.calls["embed"] += 1
        return self.feed(image)


def test_step_naive_realsize_encoder(world, benchmark, record_cost):
    """The REAL DINOv2-S architecture (random init, 224 px, 22M parameters) in the loop: what
    caching saves once the encoder is no longer a toy. One step per call."""
    import timm

    from encoders import get_spec
    from encoders.timm_encoders import TimmEncoder

    if world.name != "pi05":
        pytest.skip("one backbone is enough to show the encoder's share")
    spec = get_spec("dinov2_s")
    with torch.random.fork_rng():
        torch.manual_seed(0)
        model = timm.create_model(spec.timm_name, pretrained=False, num_classes=0,
                                  img_size=spec.input_size)
    encoder = TimmEncoder(spec, model, spec.input_size, weights_id="random-init")
    next_batch = _naive_next_batch(world, encoder)
    _time(benchmark, lambda: _train_projector(world, encoder.channels, next_batch, steps=1),
          rounds=3)
    record_cost(f"step_naive_dinov2_s_realsize/{world.name}", steps=1)
