"""Tiny released checkpoints: state dropout of the native training and the release cache key."""

from __future__ import annotations

import dataclasses

import torch

from bench.run.releases import drop_states, release_key
from bench.grid.protocol import TINY


def test_state_dropout_replaces_whole_rows_with_the_mean_at_the_given_rate():
    states = torch.arange(4000, dtype=torch.float32).reshape(500, 8)
    mean = torch.full((8,), -1.0)
    assert drop_states(states, 0.0, mean, torch.Generator().manual_seed(0)) is states
    assert (drop_states(states, 1.0, mean, torch.Generator().manual_seed(0)) == -1).all()
    half = drop_states(states, 0.5, mean, torch.Generator().manual_seed(0))
    dropped = (half == -1).all(dim=1)
    kept = (half == states).all(dim=1)
    assert (dropped | kept).all()  # a row is dropped whole or kept whole
    assert 200 < int(dropped.sum()) < 300
    again = drop_states(states, 0.5, mean, torch.Generator().manual_seed(0))
    assert torch.equal(half, again)  # the generator alone decides


def test_release_key_changes_with_the_state_dropout():
    class S:
        fingerprint = "abc"

    other = dataclasses.replace(TINY, protocol=TINY.protocol.replace(
        native_state_dropout=TINY.protocol.native_state_dropout + 0.1))
    assert release_key("smolvla", TINY, [S()], 10, "arch") != \
        release_key("smolvla", other, [S()], 10, "arch")
