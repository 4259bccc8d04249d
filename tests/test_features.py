"""pool_grid known answers and the feature store (bench.resources.features, bench.resources.feature_file: its file format)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from types import SimpleNamespace

import pytest
import torch
from torch import Tensor

from bench.resources import feature_file as fs
from bench.resources.features import FeatureStore, feature_key, pool_grid
from bench.loops.encode import encode_pooled
from ondisk.paths import REPO_ROOT
from encoders import build_encoder

CAMERAS = ("observation.images.image", "observation.images.wrist_image")


@dataclass
class FakeSuite:
    """Just what the store reads of a Suite: frame f's image is a fixed function of f."""

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
    """Wraps an encoder and counts forward calls (spec/weights_id passed through, so it shares
    the inner encoder's store); `delay_s` per call slows a build down for the kill test."""

    def __init__(self, inner, delay_s: float = 0.0):
        super().__init__()
        self.inner, self.calls, self.delay_s = inner, 0, delay_s
        self.spec, self.weights_id, self.channels = inner.spec, inner.weights_id, inner.channels
        self.input_size = inner.input_size

    def forward(self, images):
        self.calls += 1
        time.sleep(self.delay_s)
        return self.inner(images)


def everything(views: dict) -> dict[str, Tensor]:
    """{camera: view} -> {camera: (N, T, C)}: every frame read."""
    return {c: v[torch.arange(len(v))] for c, v in views.items()}


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


def test_store_round_trip_is_built_once_and_opened_once(tmp_path):
    suite = FakeSuite()
    enc = CountingEncoder(build_encoder("repvit", "tiny"))
    store = FeatureStore(tmp_path, dtype="float32", progress=False, chunk_frames=4)
    first = everything(store.pooled_features(enc, suite, (2, 2)))
    assert set(first) == set(CAMERAS)
    assert first[CAMERAS[0]].shape == (10, 4, 64) and first[CAMERAS[0]].dtype == torch.float32
    assert enc.calls == 1 + 3 * len(CAMERAS)  # the grid probe, then ceil(10 / 4) chunks
    layout = store.stored(enc, suite).layout
    assert layout.grid == (2, 2)  # the tiny RepViT's own grid
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{layout.key}.feat",
                                                          f"{layout.key}.feat.lock"]
    # The same session: the open file is reused, the encoder is not called again.
    again = everything(store.pooled_features(enc, suite, (1, 1)))
    assert enc.calls == 1 + 3 * len(CAMERAS)
    assert torch.allclose(again[CAMERAS[1]][:, 0], first[CAMERAS[1]].mean(1), atol=1e-6)
    # A later session: one probe call, then the completed file is read, not recomputed.
    later = everything(FeatureStore(tmp_path, dtype="float32", progress=False)
                       .pooled_features(enc, suite, (2, 2)))
    assert enc.calls == 2 + 3 * len(CAMERAS)
    for camera in CAMERAS:
        assert torch.equal(first[camera], later[camera])


@pytest.mark.parametrize("grid", [(1, 1), (2, 2), (3, 3), (4, 4), (8, 8)])
@pytest.mark.parametrize("encoder", ["siglip", "dinov2_s", "fastvit", "pixels"])
def test_float32_store_equals_the_encoder_pooled_directly(tmp_path, encoder, grid):
    suite = FakeSuite(n_frames=7)
    enc = build_encoder(encoder, "tiny")
    views = FeatureStore(tmp_path, dtype="float32", progress=False,
                         chunk_frames=5).pooled_features(enc, suite, grid)
    # What the pre-store cache held: encode_pooled over the same chunks, concatenated. Stored at
    # the encoder's grid and pooled per batch, float32 gives exactly those numbers.
    chunks = [encode_pooled(enc, suite.images(torch.arange(a, min(a + 5, 7))), grid)
              for a in (0, 5)]
    frames = torch.tensor([6, 0, 3])
    live = encode_pooled(enc, suite.images(frames), grid)  # other batches: other float sums
    for camera in CAMERAS:
        assert views[camera].shape == (7, grid[0] * grid[1], enc.channels)
        direct = torch.cat([c[camera] for c in chunks])
        assert torch.equal(views[camera][frames], direct[frames])
        assert torch.allclose(views[camera][frames], live[camera], atol=1e-6)


@pytest.mark.parametrize("dtype", ["bf16", "fp16"])
def test_half_store_is_the_float32_grid_rounded_then_pooled(tmp_path, dtype):
    suite = FakeSuite(n_frames=5)
    enc = build_encoder("siglip", "tiny")
    full = FeatureStore(tmp_path, dtype="float32", progress=False)
    half = FeatureStore(tmp_path, dtype=dtype, progress=False)
    own = full.stored(enc, suite).layout.grid
    exact = everything(full.pooled_features(enc, suite, own))
    rounded = everything(half.pooled_features(enc, suite, own))
    torch_dtype = fs.DTYPES[dtype]
    for camera in CAMERAS:
        assert torch.equal(rounded[camera], exact[camera].to(torch_dtype).float())
    # Pooled targets: within the dtype's rounding of the float32 ones.
    coarse = everything(half.pooled_features(enc, suite, (2, 2)))[CAMERAS[0]]
    ref = everything(full.pooled_features(enc, suite, (2, 2)))[CAMERAS[0]]
    eps = torch.finfo(torch_dtype).eps
    assert 0 < (coarse - ref).abs().max() <= eps * ref.abs().max()
    assert half.path(half.stored(enc, suite).layout).stat().st_size < full.path(
        full.stored(enc, suite).layout).stat().st_size * 0.51


def test_store_key_changes_with_grid_fingerprint_encoder_and_dtype():
    suite = FakeSuite()
    enc = build_encoder("blind", "tiny")
    base = feature_key(enc, suite, (8, 8))
    assert feature_key(enc, suite, (8, 8)) == base
    assert feature_key(enc, suite, (16, 16)) != base
    assert feature_key(enc, FakeSuite(fingerprint="fp-2"), (8, 8)) != base
    assert feature_key(build_encoder("pixels", "tiny"), suite, (8, 8)) != base
    assert feature_key(enc, suite, (8, 8), "bf16") != base


def test_one_file_serves_coarse_and_fine_grids(tmp_path):
    suite = FakeSuite(n_frames=3)
    enc = CountingEncoder(build_encoder("pixels", "tiny"))
    store = FeatureStore(tmp_path, dtype="float32", progress=False)
    coarse = everything(store.pooled_features(enc, suite, (1, 1)))
    fine = everything(store.pooled_features(enc, suite, (2, 2)))
    finer = everything(store.pooled_features(enc, suite, (16, 16)))  # pool_double-like
    assert enc.calls == 1 + len(CAMERAS)  # probe + one chunk: one extraction for all grids
    assert [p.suffix for p in tmp_path.iterdir() if p.suffix != ".lock"] == [".feat"]
    assert coarse[CAMERAS[0]].shape == (3, 1, 192) and fine[CAMERAS[0]].shape == (3, 4, 192)
    # pixels (mean-centred) + (1, 1) pooling: averaged over patch positions, zero per colour;
    # (2, 2) pooling: each quadrant's mean colour minus the image's.
    image = suite.images(torch.tensor([1]))[CAMERAS[1]][0]
    assert torch.allclose(coarse[CAMERAS[1]][1, 0].reshape(3, 64).mean(1), torch.zeros(3),
                          atol=1e-6)
    rows, cols = image.shape[1] // 2, image.shape[2] // 2
    top_left = image[:, :rows, :cols].mean((1, 2)) - image.mean((1, 2))
    assert torch.allclose(fine[CAMERAS[1]][1, 0].reshape(3, 64).mean(1), top_left, atol=1e-6)
    # 16x16 from the stored 8x8: each stored cell repeated 2x2, nothing else.
    stored = everything(store.pooled_features(enc, suite, (8, 8)))[CAMERAS[0]]
    grid = finer[CAMERAS[0]].reshape(3, 16, 16, 192)
    assert torch.equal(grid[:, ::2, ::2].reshape(3, 64, 192), stored)
    assert torch.equal(grid[:, 1::2, 1::2].reshape(3, 64, 192), stored)


def test_views_index_like_tensors_and_apply_the_transform_per_batch(tmp_path):
    suite = FakeSuite(n_frames=6)
    enc = build_encoder("dinov2_s", "tiny")
    store = FeatureStore(tmp_path, dtype="bf16", progress=False)
    plain = everything(store.pooled_features(enc, suite, (2, 2)))
    seen = []

    def plant(features, rows):
        seen.append(rows.tolist())
        return {k: v + rows.view(-1, 1, 1) * 1000 for k, v in features.items()}

    views = store.pooled_features(enc, suite, (2, 2), transform=plant)
    view = views[CAMERAS[0]]
    got = view[torch.tensor([4, 1, 4])]
    assert torch.equal(got, plain[CAMERAS[0]][[4, 1, 4]] + torch.tensor([4, 1, 4.0])
                       .view(-1, 1, 1) * 1000)
    assert seen == [[4, 1, 4]]
    assert view[torch.tensor(2)].shape == (4, 64)  # a 0-d index drops the frame axis
    assert view[torch.tensor([[0, 1], [2, 3]])].shape == (2, 2, 4, 64)
    with pytest.raises(IndexError, match="outside 0..5"):
        view[torch.tensor([6])]


def test_empty_suite_is_an_error(tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        FeatureStore(tmp_path, progress=False).pooled_features(
            build_encoder("blind", "tiny"), FakeSuite(n_frames=0), (1, 1))


def test_a_store_that_does_not_fit_is_refused_before_writing(tmp_path, monkeypatch):
    lines = []
    monkeypatch.setattr(fs.shutil, "disk_usage", lambda p: SimpleNamespace(free=10_000))
    layout = fs.Layout("k", CAMERAS, 1000, (16, 16), 768, "bf16")
    with pytest.raises(fs.StoreDoesNotFit) as info:
        fs.build(tmp_path / "k.feat", layout, lambda a, b: {}, 64, say=lines.append)
    message = str(info.value)
    assert "\n" not in message and "--features loop" in message and "GRAFTBENCH_CACHE" in message
    assert "0.79 GB" in lines[0] and "GB free" in lines[0]  # 2 x 1000 x 256 x 768 x 2 bytes
    assert not (tmp_path / "k.feat").exists() and not fs.progress_path(tmp_path / "k.feat").exists()


def test_fp16_overflow_is_an_error_naming_bf16(tmp_path):
    layout = fs.Layout("k", ("cam",), 2, (1, 1), 2, "fp16")
    huge = {"cam": torch.full((2, 1, 2), 1e6)}
    with pytest.raises(ValueError, match="bf16"):
        fs.build(tmp_path / "k.feat", layout, lambda a, b: huge, 2)


def test_a_damaged_completed_file_is_never_read(tmp_path):
    layout = fs.Layout("k", ("cam",), 3, (1, 1), 4, "float32")
    data = {"cam": torch.arange(12.0).reshape(3, 1, 4)}
    stored = fs.build(tmp_path / "k.feat", layout, lambda a, b: {"cam": data["cam"][a:b]}, 2)
    assert torch.equal(stored.read(0, [2, 0]), data["cam"][[2, 0]])
    stored.verify()
    stored.close()
    with pytest.raises(fs.StoreInvalid, match="expected"):
        fs.StoredFeatures.open(tmp_path / "k.feat", expect=layout.__class__(
            "other", ("cam",), 3, (1, 1), 4, "float32"))
    raw = bytearray((tmp_path / "k.feat").read_bytes())
    raw[5] ^= 0xFF  # flip a data byte: the footer is intact, the chunk crc32 is not
    (tmp_path / "k.feat").write_bytes(raw)
    with pytest.raises(fs.StoreInvalid, match="chunk 0"):
        fs.StoredFeatures.open(tmp_path / "k.feat", expect=layout).verify()
    (tmp_path / "k.feat").write_bytes(raw[:-1])  # torn footer
    with pytest.raises(fs.StoreInvalid):
        fs.StoredFeatures.open(tmp_path / "k.feat", expect=layout)


def test_reads_in_flight_together_give_what_one_at_a_time_gives(tmp_path, monkeypatch):
    layout = fs.Layout("k", ("a", "b"), 50, (2, 3), 8, "bf16")
    values = torch.randn(50, 6, 8, generator=torch.Generator().manual_seed(0))
    stored = fs.build(tmp_path / "k.feat", layout,
                      lambda s, e: {"a": values[s:e], "b": -values[s:e]}, 16)
    frames = [49, 0, 7, 7, 31, 12, 3, 48, 20, 1, 44]
    one_at_a_time = stored.read(1, frames)
    monkeypatch.setattr(fs, "PARALLEL_READ_BYTES", 0)
    assert torch.equal(stored.read(1, frames), one_at_a_time)
    assert torch.equal(one_at_a_time, (-values[frames]).to(torch.bfloat16).float())


def test_resume_recomputes_from_the_first_chunk_that_fails_its_crc(tmp_path):
    layout = fs.Layout("k", ("cam",), 6, (1, 1), 2, "float32")
    values = torch.arange(12.0).reshape(6, 1, 2)
    asked = []

    def compute(a, b):
        asked.append(a)
        return {"cam": values[a:b]}

    def stop_after_two(done, total):
        if done == 4:
            raise KeyboardInterrupt  # stands in for a crash right after chunk 2's commit

    path = tmp_path / "k.feat"
    with pytest.raises(KeyboardInterrupt):
        fs.build(path, layout, compute, 2, chunk_done=stop_after_two)
    assert asked == [0, 2] and not path.exists()
    with open(fs.partial_path(path), "r+b") as f:  # a torn write inside committed chunk 2
        f.seek(layout.offset(0, 3))
        f.write(b"\xff" * 8)
    asked.clear()
    stored = fs.build(path, layout, compute, 2)
    assert asked == [2, 4]  # chunk 1 kept, chunk 2 recomputed, chunk 3 new
    assert torch.equal(stored.read(0, range(6)), values)
    assert not fs.partial_path(path).exists() and not fs.progress_path(path).exists()


KILLED_BUILD = """
import sys
sys.path.insert(0, {repo!r})
from bench.resources.features import FeatureStore
from encoders import build_encoder
from tests.test_features import CountingEncoder, FakeSuite

def committed(done, total):
    print(done, flush=True)

enc = CountingEncoder(build_encoder("pixels", "tiny"), delay_s=0.15)
FeatureStore({root!r}, dtype="bf16", progress=False, chunk_frames=4,
             chunk_done=committed).stored(enc, FakeSuite(n_frames=40))
print("finished", flush=True)
"""


@pytest.mark.slow  # a build in a fresh interpreter, killed midway
def test_a_killed_build_is_never_read_and_the_rerun_completes_it(tmp_path):
    root = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-c", KILLED_BUILD.format(repo=str(REPO_ROOT),
                                                                        root=str(root))],
                             stdout=subprocess.PIPE, text=True, env={**os.environ})
    for line in child.stdout:
        if int(line) >= 12:  # 3 of 10 chunks committed
            child.send_signal(signal.SIGKILL)
            break
    assert child.wait(timeout=60) == -signal.SIGKILL

    suite = FakeSuite(n_frames=40)
    enc = CountingEncoder(build_encoder("pixels", "tiny"))
    store = FeatureStore(root, dtype="bf16", progress=False, chunk_frames=4)
    layout = store.layout(enc, suite)
    path = store.path(layout)
    # (a) nothing a reader trusts: no completed file; the partial one has no footer.
    assert not path.exists() and fs.partial_path(path).exists()
    with pytest.raises(fs.StoreInvalid, match="not a completed store"):
        fs.StoredFeatures.open(fs.partial_path(path))
    committed = len(json.loads(fs.progress_path(path).read_text())["crc32"])
    assert 3 <= committed < 10
    # (b) the rerun computes only the chunks not committed, and completes the file.
    enc.calls = 0
    resumed = everything(store.pooled_features(enc, suite, (8, 8)))
    assert enc.calls == 1 + (10 - committed) * len(CAMERAS)  # the grid probe, then the rest
    assert path.exists() and not fs.partial_path(path).exists()
    store.stored(enc, suite).verify()
    # (c) what it holds equals a clean, uninterrupted build, exactly.
    clean = everything(FeatureStore(tmp_path / "clean", dtype="bf16", progress=False,
                                    chunk_frames=4).pooled_features(enc, suite, (8, 8)))
    for camera in CAMERAS:
        assert torch.equal(resumed[camera], clean[camera])
