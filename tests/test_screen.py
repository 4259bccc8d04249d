"""bench.screen on the tiny world: a screen from the feature store, and the known-answer
ladder (falling resolution, then rising noise, down to blind) whose planted order every
supervised proxy must recover exactly (Kendall tau = 1); the label-free entropy is measured."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bench.analysis.agreement import Undefined, is_defined, kendall_tau_b
from bench.screen.measure import measure_screen, screen_features
from bench.screen.proxies import supervised_proxies
from bench.screen.records import ScreenConditions, ScreenScores
from bench.screen.selection import (ScreenOptions, ShortScores, parse_screen_keep,
                                    select_for_graft)

SUITE = "spatial"
# (resolution of the camera image, noise sigma on its pixels); then blind. Information falls by
# construction: 4x4 is an average of 8x8, and the 0.03 noise is the 0.02 noise scaled by 1.5.
LADDER = ((8, 0.0), (4, 0.0), (4, 0.02), (4, 0.03))
SUPERVISED = tuple(p.name for p in supervised_proxies())
# What the records say they were measured under: only the scores are read here.
CONDITIONS = ScreenConditions("protocol", "normaliser", "fp16")


def screen(ws, encoder: str, backbone: str = "smolvla") -> ScreenScores:
    return measure_screen(ws, encoder, backbone, SUITE, CONDITIONS).scores


def coarse_pixels(suite) -> dict[int, dict]:
    """{r: {camera: (N, 1, 3*r*r)}} for every resolution of LADDER: each image average-pooled to
    r x r and flattened; the suite's images are read once."""
    n = len(suite.state)
    sizes = sorted({r for r, _ in LADDER})
    parts = {r: {k: [] for k in suite.camera_keys} for r in sizes}
    for start in range(0, n, 512):
        images = suite.images(torch.arange(start, min(n, start + 512)))
        for k in suite.camera_keys:
            for r in sizes:
                parts[r][k].append(F.adaptive_avg_pool2d(images[k].float(), r).flatten(1))
    return {r: {k: torch.cat(v)[:, None, :] for k, v in views.items()}
            for r, views in parts.items()}


def with_noise(views: dict, sigma: float) -> dict:
    """`views` plus sigma x a fixed standard normal draw (seed 0: nested across sigmas)."""
    gen = torch.Generator().manual_seed(0)
    return {k: v + sigma * torch.randn(v.shape, generator=gen) for k, v in views.items()}


@pytest.fixture(scope="module")
def ladder(tiny_ws):
    suite = tiny_ws.suite(SUITE)
    pooled = coarse_pixels(suite)
    rungs = [with_noise(pooled[r], s) if s else pooled[r] for r, s in LADDER]
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


def test_a_screen_reads_the_store_and_scores_the_grafts_windows(tiny_ws):
    record = measure_screen(tiny_ws, "pixels", "smolvla", SUITE, CONDITIONS)
    assert record.conditions == CONDITIONS and record.screen_id == "smolvla-spatial-pixels"
    out = record.scores
    split = tiny_ws.split(SUITE)
    assert out.n_heldout == len(split.windows) and out.n_train == len(split.train_frames)
    cameras = len(tiny_ws.suite(SUITE).camera_keys)
    assert out.dims == {"state": 8, "state+features": 8 + cameras * 192}
    for proxy in SUPERVISED:
        assert set(out.proxies[proxy]) == {"state", "state+features", "gain"}
        assert all(np.isfinite(v) for v in out.proxies[proxy].values())
    assert out.proxies["ridge"]["state"] > 0 and out.chosen["state"]["knn_k"] >= 1
    again = ScreenScores.from_json(json.loads(json.dumps(out.to_json())))
    assert again.to_json() == out.to_json() and again.score("knn") == out.score("knn")
    blind = screen(tiny_ws, "blind")
    assert blind.entropy == 1.0  # every token of the constant grid has the same norm
    assert blind.proxies["logme"]["gain"] == 0.0  # constant features are dropped: no gain


def test_screen_bits_follow_torch_threads_not_numpys_blas_default(tiny_ws, one_torch_thread):
    """numpy's BLAS defaults to every CPU whatever torch's threads: a serial run and an xdist
    worker then gave LogME and ridge 13th-digit apart (CI). The screen pins it to torch's count."""
    from threadpoolctl import threadpool_limits

    proxies = []
    for blas_threads in (1, 2):
        with threadpool_limits(blas_threads, user_api="blas"):
            proxies.append(screen(tiny_ws, "pixels").proxies)
    assert proxies[0] == proxies[1]


@pytest.mark.parametrize("value, expected", [("3", 3), ("all", None), ("12", 12)])
def test_screen_keep_accepts_counts_and_all(value, expected):
    assert parse_screen_keep(value) == expected


def test_screen_keep_refuses_a_keyword_in_another_case():
    """Keywords are lower case on every option (--robustness ALL is refused too)."""
    with pytest.raises(ValueError, match=r"^--screen-keep ALL: keywords are lower case; give "
                                         r"--screen-keep all$"):
        parse_screen_keep("ALL")


@pytest.mark.parametrize("value", ["0", "-2", "2.5", "three", ""])
def test_screen_keep_refuses_in_one_line(value):
    with pytest.raises(ValueError, match=r"^--screen-keep .*: give a whole number >= 1, or all$"):
        parse_screen_keep(value)


def fake_screen(encoder: str, gain) -> ScreenScores:
    out = ScreenScores(encoder, "smolvla", SUITE)
    out.proxies = {p: {"gain": gain} for p in SUPERVISED}
    return out


def test_select_for_graft_keeps_the_top_and_says_what_it_dropped():
    screens = [fake_screen("a", 0.1), fake_screen("b", 0.3), fake_screen("c", 0.2),
               fake_screen("d", Undefined("all 4 feature columns constant")),
               fake_screen("pixels", -1.0)]
    stored = ScreenScores.from_json(json.loads(json.dumps(screens[3].to_json())))
    assert stored.score("ridge") == Undefined("all 4 feature columns constant")
    chosen = select_for_graft("smolvla", SUITE, screens, ScreenOptions(2, "ridge"), ("pixels",),
                              {"e": "RuntimeError: no weights"})
    assert chosen.kept == ("b", "c") and chosen.note is None
    assert chosen.grafts("pixels") and not chosen.grafts("a")  # a reference is never ranked
    assert chosen.dropped["a"] == "ridge rank 3 of 3 (0.1), below the top 2"
    assert "constant" in chosen.dropped["d"] and "no weights" in chosen.dropped["e"]
    chosen = select_for_graft("smolvla", SUITE, screens, ScreenOptions(5, "logme"))
    assert chosen.kept == ("b", "c", "a", "pixels") and "more than the 4" in chosen.note
    assert select_for_graft("smolvla", SUITE, screens, ScreenOptions(None, "knn")).kept == (
        "b", "c", "a", "pixels")
    with pytest.raises(ValueError, match="--screen-by shortest: unknown proxy; choose one of"):
        select_for_graft("smolvla", SUITE, screens, ScreenOptions(1, "shortest"))


def test_select_by_short_keeps_the_lowest_short_graft_mse():
    shorts = [ShortScores("a", 0.30), ShortScores("b", 0.10), ShortScores("c", 0.20),
              ShortScores("d", Undefined("its short graft failed: boom"))]
    chosen = select_for_graft("smolvla", SUITE, shorts, ScreenOptions(1, "short"))
    assert chosen.kept == ("b",) and chosen.by == "short"
    assert chosen.dropped["a"] == "short rank 3 of 3 (MSE 0.3), below the top 1"
    assert "boom" in chosen.dropped["d"]
