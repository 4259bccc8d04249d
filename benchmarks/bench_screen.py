"""The screen tier beside the graft it screens for, in one run (a screen should cost under 5% of
a graft), and the screen's proxies at the real study's size:

    .venv/bin/pytest benchmarks/bench_screen.py --benchmark-only -p no:randomly
    .venv/bin/pytest benchmarks/bench_screen.py --benchmark-only -p no:randomly -k synthetic
    .venv/bin/pytest benchmarks/bench_screen.py --benchmark-only -p no:randomly -k real_store \
        --benchmark-timer time.process_time

test_proxies_synthetic: every supervised proxy of the table on one [state, features] input set
of N = 721 training windows (5 episode folds) and 144 held out, D = 8 + 2,568 float32 columns,
C = 350 targets (bench.screen.synthetic), one BLAS thread; `planted`: features that carry the
task, `random`: features of an independent latent (the random-init twin's case). A fresh
FitInputs each round (its decomposition is cached on it). The goal: about a second, a few
percent of a 600-step tiny graft (22-34 s on this machine class).

test_screen_real_store: one whole screen (read, pool, every proxy on both input sets, entropy)
from a completed fp16 store at studies/real's shapes (Lite0 7x7x1280 and Lite2 9x9x1280, Lite0's
stride-16 tap 14x14x112, DINOv2-S 16x16x384 channels-last; 1,082 frames x 2 cameras, 721
training windows in 5 folds, 122 held out, pooled to the tiny backbones' 2x2 / 4x4 grids).

Per encoder on the tiny profile (SmolVLA, spatial, seed 0): one graft cell through
bench.cell.service.run_cell (1 round: a cell takes ~10-30 s on 2 cores), then its screen through
bench.screen.measure.measure_screen (3 rounds). The feature store is built before either is timed
(both read the same stored features; extraction is the graft's cost too). The goal: the screen's
minimum at most 5% of the graft cell's.
"""

from __future__ import annotations

import tempfile

from bench.progress import QUIET
import pytest

ENCODERS = ("dinov2_s", "pixels")
BACKBONE, SUITE = "smolvla", "spatial"
GRAFT_SECONDS: dict[str, float] = {}


@pytest.fixture(scope="module")
def workspace():
    from bench.grid.protocol import TINY
    from bench.results.store import ResultStore
    from bench.resources.workspace import Workspace

    ws = Workspace(TINY, ResultStore(tempfile.mkdtemp(prefix="bench-screen-")), progress=QUIET)
    for encoder in ENCODERS:  # build the stores and load the policy outside the timings
        bb = ws.backbone(BACKBONE, SUITE)
        ws.features(encoder, SUITE, tuple(bb.info.native_grid))
    return ws


@pytest.mark.parametrize("encoder", ENCODERS)
def test_graft_cell(benchmark, workspace, encoder):
    from bench.grid.cells import CellSpec
    from bench.cell.service import run_cell

    cell = CellSpec("graft", BACKBONE, SUITE, 0, encoder)
    benchmark.pedantic(run_cell, args=(cell, workspace), rounds=1, iterations=1)
    GRAFT_SECONDS[encoder] = benchmark.stats.stats.min


@pytest.mark.parametrize("encoder", ENCODERS)
def test_screen(benchmark, workspace, encoder):
    from bench.screen.measure import measure_screen
    from bench.screen.records import ScreenConditions

    conditions = ScreenConditions("benchmark", "benchmark", "fp16")  # only the time is read
    benchmark.pedantic(measure_screen, args=(workspace, encoder, BACKBONE, SUITE, conditions),
                       rounds=3, iterations=1)
    screen = benchmark.stats.stats.min
    graft = GRAFT_SECONDS.get(encoder)
    if graft:
        benchmark.extra_info.update(graft_s=graft, ratio=screen / graft)
        print(f"\n{encoder}: screen {screen:.2f} s, graft cell {graft:.1f} s, "
              f"ratio {100 * screen / graft:.1f}% (goal <= 5%)")


@pytest.mark.parametrize("kind", ["planted", "random"])
def test_proxies_synthetic(benchmark, kind):
    from threadpoolctl import threadpool_limits

    from bench.screen.proxies import FitInputs, supervised_proxies
    from bench.screen.synthetic import synthetic_fit

    made = synthetic_fit(signal=kind == "planted")
    arrays = (made.train, made.train_targets, made.train_fold, made.heldout_features,
              made.heldout_targets, made.weights)

    def every_proxy(fit: FitInputs) -> dict:
        return {p.name: p.compute(fit) for p in supervised_proxies()}

    with threadpool_limits(1, user_api="blas"):
        out = benchmark.pedantic(every_proxy, setup=lambda: ((FitInputs(*arrays),), {}),
                                 rounds=3, iterations=1)
    benchmark.extra_info.update({name: str(value) for name, value in out.items()})
    print(f"\n{kind}: {benchmark.stats.stats.min:.2f} s (min of 3), {out}")


# studies/real's stored grids (fp16, 1,082 frames x 2 cameras): (grid, channels, memory format)
# and the tiny backbone's grid it is pooled to (SmolVLA 2x2, pi0.5 4x4).
REAL_STORES = {"effnet_lite0-smolvla": ((7, 7), 1280, "nchw", (2, 2)),
               "effnet_lite2-pi05": ((9, 9), 1280, "nchw", (4, 4)),
               "effnet_lite0_s4-smolvla": ((14, 14), 112, "nchw", (2, 2)),
               "dinov2_s_focus-pi05": ((16, 16), 384, "nhwc", (4, 4))}
REAL_FRAMES, REAL_EPISODES, HELD_OUT = 1082, 12, (3, 7, 11)


def _real_store(root, name: str):
    """A completed fp16 store at `name`'s shapes: ReLU units of a per-episode latent walk."""
    import torch

    from bench.resources import feature_file as fs

    grid, channels, memory_format, _ = REAL_STORES[name]
    layout = fs.Layout(name, ("cam0", "cam1"), REAL_FRAMES, grid, channels, "fp16", memory_format)
    gen = torch.Generator().manual_seed(0)
    latent = torch.cumsum(torch.randn(REAL_FRAMES, 12, generator=gen) * 0.3, 0)
    mix = torch.randn(12, channels, generator=gen)

    def compute(start: int, stop: int) -> dict:
        tokens = grid[0] * grid[1]
        return {c: torch.relu((latent[start:stop] @ mix)[:, None, :] + 0.5 * torch.randn(
            stop - start, tokens, channels, generator=gen)) for c in layout.cameras}

    return fs.build(root / f"{name}.feat", layout, compute, 128)


def _real_world():
    """(suite, split) with studies/real's sizes: 721 training windows in 9 episodes, 122 held
    out."""
    from types import SimpleNamespace

    import torch

    gen = torch.Generator().manual_seed(0)
    episode = torch.arange(REAL_FRAMES) * REAL_EPISODES // REAL_FRAMES
    suite = SimpleNamespace(state=torch.randn(REAL_FRAMES, 8, generator=gen),
                            action=torch.randn(REAL_FRAMES, 7, generator=gen),
                            episode_index=episode)
    held = torch.isin(episode, torch.tensor(HELD_OUT))
    split = SimpleNamespace(train_frames=torch.nonzero(~held).flatten()[:721],
                            train_episodes=[e for e in range(REAL_EPISODES) if e not in HELD_OUT],
                            windows=torch.nonzero(held).flatten()[::3][:122])
    return suite, split


@pytest.mark.parametrize("name", sorted(REAL_STORES))
def test_screen_real_store(benchmark, tmp_path_factory, name):
    """One whole screen (bench.screen.measure.screen_features: read and pool both cameras'
    stored grids, every proxy on [state] and [state, features], entropy) from a store at
    studies/real's shapes, one thread; the goal: <= 5% of a tiny graft cell (22-34 s here)."""
    from bench.resources.features import PooledView
    from bench.screen.measure import screen_features

    stored = _real_store(tmp_path_factory.mktemp("real-store"), name)
    views = {c: PooledView(stored, c, REAL_STORES[name][3]) for c in stored.layout.cameras}
    suite, split = _real_world()
    benchmark.pedantic(screen_features, args=(views, suite, split, lambda a: 0.5 * a, 50,
                                              (name, "smolvla", "spatial")),
                       rounds=3, iterations=1)
    print(f"\n{name}: {benchmark.stats.stats.min:.2f} s (min of 3)")
