"""The closed-loop controller runs the offline scoring path: same actions for the same noise.

No simulator needed: observations are held-out frames of the tiny suite, shaped as LIBERO's env
hands them over (images, state, task; no action keys).
"""

from __future__ import annotations

import pytest
import torch

from bench.grid.cells import CellSpec
from bench.run.closed_loop import (
    NO_CLOSED_LOOP, cell_act, make_act, observation_noise,
)
from bench.run.features import encode_pooled
from bench.run.graft import GraftFeed, Projector
from bench.suites.windows import raw_batch
from bench.run.train import frozen_autocast


def observations(ws, n=6):
    suite, split = ws.suite("spatial"), ws.split("spatial")
    raw = raw_batch(suite, split.windows[:n], 10)
    return {k: v for k, v in raw.items() if k not in ("action", "action_is_pad")}


def offline_actions(backbone, obs, noise, feed=None, features=None):
    """What bench.run.evaluate.score computes for these windows, in raw units."""
    info = backbone.info
    raw = {**obs, "action": torch.zeros((len(obs["task"]), info.chunk_size, 7)),
           "action_is_pad": torch.zeros((len(obs["task"]), info.chunk_size), dtype=torch.bool)}
    batch = backbone.preprocess(raw)
    if feed is not None:
        feed.bind(features)
        with backbone.image_embedder(feed), frozen_autocast(torch.device("cpu")):
            pred = backbone.sample_actions(batch, noise)
    else:
        pred = backbone.sample_actions(batch, noise)
    return backbone.unnormalize_actions(pred[..., :7]).float()


@pytest.mark.parametrize("backbone_name", ["smolvla", "pi05"])
def test_native_act_is_the_offline_sampler_with_observation_noise(tiny_ws, backbone_name):
    backbone = tiny_ws.backbone(backbone_name)
    obs = observations(tiny_ws)
    act = make_act(backbone, noise_seed=3)
    out = act(obs)
    assert out.shape == (6, backbone.info.chunk_size, 7)
    noise = observation_noise(obs, backbone.info.chunk_size, backbone.info.max_action_dim, 3)
    torch.testing.assert_close(out, offline_actions(backbone, obs, noise))
    torch.testing.assert_close(act(obs), out, rtol=0, atol=0)  # deterministic, no counter
    # Row noise depends on the row's own observation only: a sub-batch gets the same rows.
    sub = {k: v[2:4] for k, v in obs.items()}
    torch.testing.assert_close(act(sub), out[2:4], rtol=1e-5, atol=1e-5)


def test_graft_act_encodes_live_pixels_like_the_feature_cache(tiny_ws):
    backbone = tiny_ws.backbone("pi05")
    encoder = tiny_ws.encoder("pixels")
    grid = backbone.info.native_grid
    torch.manual_seed(0)
    projector = Projector(encoder.channels, backbone.info.lm_width).eval()
    feed = GraftFeed(projector, backbone.camera_keys, grid)
    obs = observations(tiny_ws)
    cell = CellSpec("graft", "pi05", "spatial", 0, "pixels")
    out = cell_act(cell, backbone, noise_seed=1, feed=feed, encoder=encoder, grid=grid)(obs)
    noise = observation_noise(obs, backbone.info.chunk_size, backbone.info.max_action_dim, 1)
    frames = tiny_ws.split("spatial").windows[:6]
    stored, tiny_ws.feature_dtype = tiny_ws.feature_dtype, "float32"  # the encoder's own numbers
    try:
        cached = tiny_ws.features("pixels", "spatial", grid)
        expected = offline_actions(backbone, obs, noise, feed,
                                   {k: v[frames] for k, v in cached.items()})
    finally:
        tiny_ws.feature_dtype = stored
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)
    # zero_image cells see black frames in closed loop too: not the same actions.
    zero = CellSpec("zero_image", "pi05", "spatial", 0, "pixels", "eval")
    blank = cell_act(zero, backbone, noise_seed=1, feed=feed, encoder=encoder, grid=grid)(obs)
    zeros = encode_pooled(encoder, {k: torch.zeros_like(obs[k]) for k in backbone.camera_keys}, grid)
    torch.testing.assert_close(blank, offline_actions(backbone, obs, noise, feed, zeros),
                               rtol=1e-4, atol=1e-5)
    assert not torch.allclose(blank, out)


def test_missing_observation_keys_are_named(tiny_ws):
    act = make_act(tiny_ws.backbone("pi05"), noise_seed=0)
    obs = observations(tiny_ws, 2)
    del obs["observation.state"]
    with pytest.raises(KeyError, match="observation.state"):
        act(obs)


def test_resume_rule_for_rollouts():
    """bench.results.current resumes a record with --rollouts N only when it holds N episodes per
    task (or its kind's skip line)."""
    from bench.results.record import RunInfo

    assert not RunInfo().has_rollouts(5)
    assert RunInfo(rollouts={"spec": {"episodes_per_task": 5}}).has_rollouts(5)
    assert not RunInfo(rollouts={"spec": {"episodes_per_task": 2}}).has_rollouts(5)
    assert RunInfo(rollouts={"skipped": NO_CLOSED_LOOP["shuffled"]}).has_rollouts(5)
