"""bench.run.screen on the tiny world: a screen cell from the feature store, and the known-answer
ladder (falling resolution, then rising noise, down to blind) whose planted order every
supervised proxy must recover exactly (Kendall tau = 1); the label-free entropy is measured."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bench.analysis.agreement import is_defined, kendall_tau_b
from bench.run.screen import SUPERVISED, screen_cell, screen_features

SUITE = "spatial"
# (resolution of the camera image, noise sigma on its pixels); then blind. Information falls by
# construction: 4x4 is an average of 8x8, and the 0.03 noise is the 0.02 noise scaled by 1.5.
LADDER = ((8, 0.0), (4, 0.0), (4, 0.02), (4, 0.03))


def coarse_pixels(suite, resolution: int, sigma: float) -> dict:
    """{camera: (N, 1, 3*r*r)}: each image average-pooled to r x r, flattened, plus fixed noise."""
    n = len(suite.state)
    parts = {k: [] for k in suite.camera_keys}
    for start in range(0, n, 512):
        images = suite.images(torch.arange(start, min(n, start + 512)))
        for k in suite.camera_keys:
            parts[k].append(F.adaptive_avg_pool2d(images[k].float(), resolution).flatten(1))
    views = {k: torch.cat(v)[:, None, :] for k, v in parts.items()}
    gen = torch.Generator().manual_seed(0)
    return {k: v + sigma * torch.randn(v.shape, generator=gen) for k, v in views.items()}


@pytest.fixture(scope="module")
def ladder(tiny_ws):
    suite = tiny_ws.suite(SUITE)
    rungs = [coarse_pixels(suite, r, s) for r, s in LADDER]
    rungs.append({k: torch.ones((len(suite.state), 1, 4)) for k in suite.camera_keys})
    return rungs


@pytest.mark.parametrize("backbone", ["smolvla", "pi05"])
def test_every_supervised_proxy_recovers_the_planted_order(tiny_ws, ladder, backbone):
    bb = tiny_ws.backbone(backbone, SUITE)
    suite, split = tiny_ws.suite(SUITE), tiny_ws.split(SUITE)
    names = [f"pixels@{r}+{s}" for r, s in LADDER] + ["blind"]
    screens = [screen_features(views, suite, split, bb.normalize_actions, bb.info.chunk_size,
                               (name, backbone, SUITE)) for name, views in zip(names, ladder)]
    planted = list(range(len(ladder), 0, -1))  # higher is better: the first rung is best
    for proxy in SUPERVISED:
        scores = [s.score(proxy) for s in screens]
        assert all(is_defined(x) for x in scores), (proxy, scores)
        assert kendall_tau_b(scores, planted) == pytest.approx(1.0), (proxy, scores)
    assert screens[-1].score("logme") == 0.0 and screens[-1].score("knn") == 0.0
    entropy = [s.score("entropy") for s in screens]  # label-free: measured, not required
    assert all(is_defined(e) and 0 <= e <= 1 for e in entropy)


def test_screen_cell_reads_the_store_and_scores_the_grafts_windows(tiny_ws):
    out = screen_cell(tiny_ws, "pixels", "smolvla", SUITE)
    split = tiny_ws.split(SUITE)
    assert out.n_heldout == len(split.windows) and out.n_train == len(split.train_frames)
    cameras = len(tiny_ws.suite(SUITE).camera_keys)
    assert out.dims == {"state": 8, "state+features": 8 + cameras * 192}
    for proxy in SUPERVISED:
        assert set(out.proxies[proxy]) == {"state", "state+features", "gain"}
        assert all(np.isfinite(v) for v in out.proxies[proxy].values())
    assert out.proxies["ridge"]["state"] > 0 and out.chosen["state"]["knn_k"] >= 1
    blind = screen_cell(tiny_ws, "blind", "smolvla", SUITE)
    assert blind.entropy == 1.0  # every token of the constant grid has the same norm
    assert blind.proxies["logme"]["gain"] == 0.0  # constant features are dropped: no gain
