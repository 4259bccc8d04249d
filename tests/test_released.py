"""Tiny released checkpoints: state dropout and image shift of the native training, and the
release cache key; the same image shift in graft training."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from bench.progress import QUIET
import pytest
import torch

from bench.results.store import ResultStore
from bench.resources.workspace import Workspace
from tests.worlds import lent_workspace
from bench.resources import releases
from bench.resources.releases import drop_states, release_key
from bench.grid.kinds import SAME, ZERO
from bench.grid.protocol import SIM, TINY
from bench.loops.augment import shift_images
from bench.loops.encode import encode_pooled
from bench.cell.inputs import CellInputs
from encoders.registry import build_encoder

BASELINE = Path(__file__).resolve().parents[1] / ".graftbench" / "baselines" / "ci-tiny.json"


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


def test_image_shift_moves_each_image_whole_by_at_most_the_pad():
    images = torch.rand(64, 3, 12, 10)
    assert shift_images(images, 0, torch.Generator().manual_seed(0)) is images
    shifted = shift_images(images, 2, torch.Generator().manual_seed(0))
    assert shifted.shape == images.shape
    padded = torch.nn.functional.pad(images, (2, 2, 2, 2), mode="replicate")
    found = set()
    for i in range(len(images)):  # each output is one crop of its own padded image
        crops = [(x, y) for y in range(5) for x in range(5)
                 if torch.equal(shifted[i], padded[i, :, y:y + 12, x:x + 10])]
        assert len(crops) == 1
        found.add(crops[0])
    assert len(found) > 15  # 64 draws over 25 offsets: the shift varies per sample
    again = shift_images(images, 2, torch.Generator().manual_seed(0))
    assert torch.equal(shifted, again)


def test_image_shift_keys_a_new_release_and_leaves_older_hashes_alone():
    class S:
        fingerprint = "abc"

    shifted = dataclasses.replace(SIM, protocol=SIM.protocol.replace(native_image_shift=4))
    assert release_key("pi05", SIM, [S()], 10, "arch") != release_key("pi05", shifted, [S()], 10,
                                                                        "arch")
    assert shifted.protocol.hash != SIM.protocol.hash
    # The committed baseline's cells were measured before the field existed: same hash today.
    assert json.loads(BASELINE.read_text())["protocol_hashes"] == [TINY.protocol.hash]


@pytest.mark.parametrize("name", ["pi05", "smolvla"])
def test_tiny_image_size_builds_the_release_at_that_size_or_refuses(tmp_path, name):
    """A 2-step release at 32 px: pi0.5's tokens follow the size (a 2 x 2 grid, a release of its
    own); SmolVLA's tiny tower reads 64 px whatever the size, so the knob is refused."""
    protocol = TINY.protocol.replace(native_steps=2, tiny_image_size=32)
    ws = Workspace(dataclasses.replace(TINY, protocol=protocol),
                   ResultStore(tmp_path / "results"), progress=QUIET, cache=tmp_path / "cache")
    ws._suites["spatial"] = lent_workspace(TINY, ResultStore(tmp_path / "r2")).suite("spatial")
    if name == "smolvla":
        with pytest.raises(ValueError, match=r"tiny_image_size = 32: the tiny smolvla reads"):
            ws.backbone(name, "spatial")
        return
    backbone = ws.backbone(name, "spatial")
    assert backbone.info.native_grid == (2, 2)
    assert tuple(backbone.policy.config.image_resolution) == (32, 32)


def test_graft_image_shift_feeds_the_encoder_moved_pixels_in_training_only(tmp_path):
    """Known answer: with graft_image_shift = 3 a training batch's features are the encoder's
    on the images shift_images moves with the cell's generator; the zero rule and evaluation
    read the images as they are."""
    assert releases.shift_images is shift_images  # one definition for native and graft training
    suite = lent_workspace(TINY, ResultStore(tmp_path / "r")).suite("spatial")
    frames = torch.arange(0, 60, 10)
    plain = CellInputs(suite, frames, frames, 4, torch.device("cpu"), (2, 2),
                       encoder=build_encoder("pixels", "tiny"))
    moved = dataclasses.replace(plain, train_shift=3, shift_seed=7)
    gen = torch.Generator().manual_seed(7)
    images = {k: shift_images(v, 3, gen) for k, v in suite.images(frames).items()}
    want = encode_pooled(plain.encoder, images, (2, 2))
    raw, got = moved.train_batches(SAME)(frames)
    _, unshifted = plain.train_batches(SAME)(frames)
    for k in suite.camera_keys:
        assert torch.equal(got[k], want[k])
        assert torch.equal(raw[k], images[k])
        assert not torch.equal(got[k], unshifted[k])
    _, zero = moved.train_batches(ZERO)(frames)
    assert all(torch.equal(zero[k], plain.zero_pooled(len(frames))[k]) for k in zero)
    pos = torch.arange(len(frames))
    scored = moved.eval_features(SAME)(pos, frames)
    assert all(torch.equal(scored[k], unshifted[k]) for k in scored)
