"""The feature store's extraction runtime (bench.resources.extraction): torch's features and
keys exactly those of the torch-only store; onnxruntime's keyed apart, close to torch's and the
same bits run to run; every failure of the onnxruntime path falls back to torch, keyed as
torch's, with its reason."""

from __future__ import annotations

import importlib.util
import sys

import pytest
import torch

from bench.resources import extraction
from bench.resources.features import FeatureStore, feature_key
from bench.loops.encode import encode_grid, encode_pooled
from encoders import build_encoder
from tests.test_features import CAMERAS, FakeSuite, everything

# feature_key(encoder, FakeSuite(), (2, 2)) as the torch-only store computed it (git 47c0a4f):
# torch's stores keep their names, so no cache is rebuilt and no number moves.
TODAYS_KEYS = {
    "dinov2_s": "2e259008ed114b50eac0d18f4d61aeee9227044fc661dfdad36184cce05f682f",
    "effnet_lite0": "62b537c86a12e287c0a96e886e1ace26c198ea898c667274ae50fd2f34b32132",
}


class ListSink:
    """A progress sink keeping its lines."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def line(self, text: str) -> None:
        self.lines.append(text)


def store(path, runtime: str, sink=False) -> FeatureStore:
    return FeatureStore(path, dtype="float32", progress=sink, chunk_frames=2, runtime=runtime)


@pytest.mark.parametrize("name", sorted(TODAYS_KEYS))
def test_torch_keys_are_todays_and_another_runtime_is_keyed_apart(name):
    enc = build_encoder(name, "tiny")
    assert feature_key(enc, FakeSuite(), (2, 2)) == TODAYS_KEYS[name]
    assert feature_key(enc, FakeSuite(), (2, 2), runtime="torch") == TODAYS_KEYS[name]
    assert feature_key(enc, FakeSuite(), (2, 2), runtime="onnxruntime==1/opset17") \
        != TODAYS_KEYS[name]


@pytest.mark.parametrize("name,runtime", [("dinov2_s", "auto"), ("effnet_lite0", "torch")])
def test_torch_runtime_gives_todays_bits(tmp_path, name, runtime):
    """The tiny ViT under "auto" (56 px: torch) and the real Lite0 under "torch": the store holds
    what the encoder's own forward gives, bit for bit, under the unchanged key."""
    enc, suite = build_encoder(name, "tiny"), FakeSuite(n_frames=3)
    views = store(tmp_path, runtime).pooled_features(enc, suite, (2, 2))
    direct = [encode_pooled(enc, suite.images(torch.arange(a, min(a + 2, 3))), (2, 2))
              for a in (0, 2)]
    for camera in CAMERAS:
        assert torch.equal(everything(views)[camera], torch.cat([d[camera] for d in direct]))
    layout = store(tmp_path, runtime).stored(enc, suite).layout
    assert layout.key == feature_key(enc, suite, layout.grid, "float32")


def test_auto_plans_onnxruntime_for_lite0_and_keys_it_so(tmp_path):
    pytest.importorskip("onnxruntime")
    enc, suite = build_encoder("effnet_lite0", "tiny"), FakeSuite(n_frames=1)
    layout = store(tmp_path, "auto").layout(enc, suite)  # no export: planned from the encoder
    assert layout.key == feature_key(enc, suite, (7, 7), "float32", extraction.onnx_tag())
    assert layout.key != store(tmp_path, "torch").layout(enc, suite).key


def test_onnxruntime_store_is_close_to_torch_and_the_same_bits_twice(tmp_path):
    pytest.importorskip("onnxruntime")
    enc, suite = build_encoder("dinov2_s", "tiny"), FakeSuite(n_frames=3)
    torch_views = everything(store(tmp_path / "torch", "torch").pooled_features(enc, suite, (2, 2)))
    builds = [store(tmp_path / str(i), "onnxruntime") for i in range(2)]  # an export each
    views = [everything(s.pooled_features(enc, suite, (2, 2))) for s in builds]
    assert builds[0].stored(enc, suite).layout.key == feature_key(
        enc, suite, (4, 4), "float32", extraction.onnx_tag())
    for camera in CAMERAS:
        assert torch.equal(views[0][camera], views[1][camera])
        assert torch.allclose(views[0][camera], torch_views[camera], rtol=0, atol=1e-5)
        assert not torch.equal(views[0][camera], torch_views[camera])  # onnxruntime's own sums


class WrongSession:
    """An export that runs but computes something else (as a BatchNorm traced in training mode
    did): zeros of the right shape."""

    def __init__(self, encoder) -> None:
        self.encoder = encoder

    def run(self, _names, feed):
        with torch.no_grad():
            return [encode_grid(self.encoder, {"c": torch.zeros(len(feed["pixels"]), 3, 8, 8)})
                    ["c"].zero_().numpy()]


def _fail_export(encoder, threads):
    raise RuntimeError("Unsupported: ONNX export of operator foo\nsecond line")


@pytest.mark.parametrize("session,reason", [
    (lambda encoder, threads: WrongSession(encoder), "its grid differs from torch's"),
    (_fail_export, "RuntimeError: Unsupported: ONNX export of operator foo)")])
def test_a_failed_export_falls_back_to_torch_keyed_as_torch(tmp_path, monkeypatch, session,
                                                             reason):
    pytest.importorskip("onnxruntime")
    monkeypatch.setattr(extraction, "_session", session)
    monkeypatch.delenv("GRAFTBENCH_QUIET", raising=False)
    enc, suite, sink = build_encoder("dinov2_s", "tiny"), FakeSuite(n_frames=2), ListSink()
    views = everything(store(tmp_path, "onnxruntime", sink).pooled_features(enc, suite, (2, 2)))
    want = encode_pooled(enc, suite.images(torch.arange(2)), (2, 2))
    assert all(torch.equal(views[c], want[c]) for c in CAMERAS)
    assert [p.name for p in tmp_path.glob("*.feat")] == \
        [feature_key(enc, suite, (4, 4), "float32") + ".feat"]
    said = [line for line in sink.lines if "extracting with torch" in line]
    assert len(said) == 1 and reason in said[0], sink.lines


def test_encoders_onnxruntime_cannot_run_stay_on_torch(monkeypatch):
    from tests.test_features import CountingEncoder

    lite0 = build_encoder("effnet_lite0", "tiny")
    wrapped = CountingEncoder(build_encoder("dinov2_s", "tiny"))  # not a timm encoder
    assert extraction.planned_tag(wrapped, "onnxruntime") == "torch"
    vit = build_encoder("dinov2_s", "tiny")
    assert extraction.planned_tag(vit, "auto") == "torch"  # 56 px: the export would not pay
    vit.input_size = 224  # as the real one (only the plan is asked: nothing runs at 224)
    assert extraction.planned_tag(vit, "auto") == "torch"  # a ViT: as quick in torch
    if importlib.util.find_spec("onnxruntime") is not None:
        assert extraction.planned_tag(vit, "onnxruntime") != "torch"  # asked for, it is tried
    assert extraction.planned_tag(lite0, "torch") == "torch"
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # as if not installed
    assert extraction.planned_tag(lite0, "auto") == "torch"
    with pytest.raises(ValueError, match="extraction runtime 'tensorrt'"):
        FeatureStore("unused", progress=False, runtime="tensorrt")
