"""pool_grid known answers and the pooled-feature cache."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch
from torch import Tensor

from bench.features import FeatureCache, encode_pooled, feature_key, pool_grid
from encoders import build_encoder

CAMERAS = ("observation.images.image", "observation.images.wrist_image")


@dataclass
class FakeSuite:
    """Just what the cache reads of a Suite: frame f's image is a fixed function of f."""

    name: str = "fake"
    fingerprint: str = "fp-1"
    camera_keys: tuple[str, ...] = CAMERAS
    n_frames: int = 10
    size: int = 64

    @property
    def state(self) -> Tensor:
        return torch.zeros(self.n_frames, 8)

    def images(self, frames: Tensor) -> dict[str, Tensor]:
        out = {}
        for k, camera in enumerate(self.camera_keys):
            batch = []
            for f in frames.tolist():
                gen = torch.Generator().manual_seed(1000 * k + f)
                batch.append(torch.rand(3, self.size, self.size, generator=gen))
            out[camera] = torch.stack(batch)
        return out


class CountingEncoder(torch.nn.Module):
    """Wraps an encoder and counts forward calls (spec/weights_id passed through)."""

    def __init__(self, inner):
        super().__init__()
        self.inner, self.calls = inner, 0
        self.spec, self.weights_id, self.channels = inner.spec, inner.weights_id, inner.channels
        self.input_size = inner.input_size

    def forward(self, images):
        self.calls += 1
        return self.inner(images)


def test_pool_grid_known_answer():
    grid = torch.arange(16.0).reshape(1, 1, 4, 4)  # rows: 0..3, 4..7, 8..11, 12..15
    grid = torch.cat([grid, -grid], dim=1)  # (1, 2, 4, 4)
    pooled = pool_grid(grid, (2, 2))
    # 2x2 block means, row-major: top-left, top-right, bottom-left, bottom-right
    expected = torch.tensor([[2.5, 4.5, 10.5, 12.5]]).T
    assert pooled.shape == (1, 4, 2)
    assert torch.equal(pooled[0], torch.cat([expected, -expected], dim=1))
    assert torch.equal(pool_grid(grid, (1, 1))[0], torch.tensor([[7.5, -7.5]]))
    # Non-square target: a (1, 2) grid averages the left and right halves.
    assert torch.equal(pool_grid(grid, (1, 2))[0, :, 0], torch.tensor([6.5, 8.5]))
    # Upsampling (target finer than the grid) repeats cells: 2x2 -> 4x4.
    small = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])
    assert pool_grid(small, (4, 4))[0, :, 0].tolist() == [1, 1, 2, 2] * 2 + [3, 3, 4, 4] * 2


def test_cache_round_trip_and_no_recompute(tmp_path):
    suite = FakeSuite()
    enc = CountingEncoder(build_encoder("repvit", "tiny"))
    cache = FeatureCache(tmp_path)
    first = cache.pooled_features(enc, suite, (2, 2), batch_size=4, progress=False)
    assert set(first) == set(CAMERAS)
    assert first[CAMERAS[0]].shape == (10, 4, 64) and first[CAMERAS[0]].dtype == torch.float32
    assert enc.calls == 3 * len(CAMERAS)  # ceil(10 / 4) batches per camera
    files = list(tmp_path.iterdir())
    assert [f.name for f in files] == [f"{feature_key(enc, suite, (2, 2))}.safetensors"]

    second = cache.pooled_features(enc, suite, (2, 2), batch_size=4, progress=False)
    assert enc.calls == 3 * len(CAMERAS)  # loaded, not recomputed
    for camera in CAMERAS:
        assert torch.equal(first[camera], second[camera])


def test_cached_features_equal_encoder_in_the_loop(tmp_path):
    suite = FakeSuite(n_frames=7)
    enc = build_encoder("siglip", "tiny")
    cached = FeatureCache(tmp_path).pooled_features(enc, suite, (3, 3), batch_size=5,
                                                    progress=False)
    frames = torch.tensor([6, 0, 3])
    live = encode_pooled(enc, suite.images(frames), (3, 3))
    for camera in CAMERAS:
        assert live[camera].shape == (3, 9, 64)
        assert torch.allclose(cached[camera][frames], live[camera], atol=1e-6)


def test_cache_key_changes_with_grid_fingerprint_and_encoder():
    suite = FakeSuite()
    enc = build_encoder("blind", "tiny")
    base = feature_key(enc, suite, (8, 8))
    assert feature_key(enc, suite, (8, 8)) == base
    assert feature_key(enc, suite, (16, 16)) != base
    assert feature_key(enc, FakeSuite(fingerprint="fp-2"), (8, 8)) != base
    assert feature_key(build_encoder("pixels", "tiny"), suite, (8, 8)) != base


def test_cache_recomputes_for_new_grid_and_write_is_atomic(tmp_path):
    suite = FakeSuite(n_frames=3)
    enc = CountingEncoder(build_encoder("pixels", "tiny"))
    cache = FeatureCache(tmp_path)
    coarse = cache.pooled_features(enc, suite, (1, 1), progress=False)
    fine = cache.pooled_features(enc, suite, (2, 2), progress=False)
    assert enc.calls == 2 * len(CAMERAS)
    assert coarse[CAMERAS[0]].shape == (3, 1, 192) and fine[CAMERAS[0]].shape == (3, 4, 192)
    # pixels (mean-centred) + (1, 1) pooling: averaged over patch positions, zero per colour;
    # (2, 2) pooling: each quadrant's mean colour minus the image's.
    image = suite.images(torch.tensor([1]))[CAMERAS[1]][0]
    assert torch.allclose(coarse[CAMERAS[1]][1, 0].reshape(3, 64).mean(1), torch.zeros(3),
                          atol=1e-6)
    rows, cols = image.shape[1] // 2, image.shape[2] // 2
    top_left = image[:, :rows, :cols].mean((1, 2)) - image.mean((1, 2))
    assert torch.allclose(fine[CAMERAS[1]][1, 0].reshape(3, 64).mean(1), top_left, atol=1e-6)
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".safetensors"] * 2  # no tmp left


def test_empty_suite_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        FeatureCache(tmp_path).pooled_features(build_encoder("blind", "tiny"),
                                               FakeSuite(n_frames=0), (1, 1), progress=False)
