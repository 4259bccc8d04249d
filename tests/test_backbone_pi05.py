"""backbones.pi05 on the tiny, offline pi0.5 (a real LeRobot PI05Policy with tiny sizes)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from backbones import paligemma_load, pi05
from backbones.base import BackboneUnavailable
from backbones.tiny_pi05 import TinyPI05Arch, tiny_pi05_patches, tiny_vocabulary

CAMERAS = ("observation.images.image", "observation.images.wrist_image")
CHUNK, STATE_DIM, ACTION_DIM = 10, 8, 7


def make_stats() -> dict:
    def one(dim: int, scale: float) -> dict:
        spread = np.linspace(0.5, 2.0, dim) * scale
        return {
            "mean": np.zeros(dim), "std": spread / 2, "min": -spread * 1.5, "max": spread * 1.5,
            "q01": -spread, "q99": spread,
        }
    return {"observation.state": one(STATE_DIM, 1.0), "action": one(ACTION_DIM, 0.5)}


def make_raw(batch: int = 2, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    raw = {key: torch.rand(batch, 3, 64, 64, generator=g) for key in CAMERAS}
    raw["observation.state"] = torch.randn(batch, STATE_DIM, generator=g)
    raw["action"] = torch.randn(batch, CHUNK, ACTION_DIM, generator=g) * 0.3
    raw["action_is_pad"] = torch.zeros(batch, CHUNK, dtype=torch.bool)
    raw["task"] = ["pick up the red block and place it on the plate", "open the top drawer"][:batch]
    return raw


def fixed_noise_time(backbone, batch: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(batch, CHUNK, backbone.info.max_action_dim, generator=g)
    return noise, backbone.sample_time(batch, g)


@pytest.fixture(scope="module")
def tiny():
    backbone = pi05.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0)
    backbone.freeze()
    return backbone


def test_tiny_build_is_a_small_real_pi05(tiny):
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    assert isinstance(tiny.policy, PI05Policy)
    assert sum(p.numel() for p in tiny.policy.parameters()) < 5_000_000
    assert tiny.info.native_grid == (4, 4) and tiny.info.lm_width == 64
    assert (tiny.info.chunk_size, tiny.info.max_action_dim, tiny.info.num_denoise_steps) == (10, 32, 10)
    assert tiny.camera_keys == CAMERAS and tuple(tiny.policy.config.image_features) == CAMERAS
    q = tiny.language_model().layers[0].self_attn
    assert hasattr(q, "q_proj") and hasattr(q, "v_proj")


def test_tiny_tokenizer_knows_every_prompt_token(tiny):
    batch = tiny.preprocess(make_raw())
    (step,) = [s for s in tiny.preprocessor.steps if type(s).__name__ == "TokenizerProcessorStep"]
    tokenizer = step.input_tokenizer
    unk = tokenizer.convert_tokens_to_ids("<unk>")
    tokens = batch["observation.language.tokens"]
    assert batch["task"][0].startswith("Task: pick up the red block") and "State: " in batch["task"][0]
    assert not (tokens == unk).any()
    assert all(str(b) in tiny_vocabulary() for b in range(256))


def test_tiny_build_is_deterministic_from_seed(tiny):
    again = pi05.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0).policy.state_dict()
    other = pi05.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=1).policy.state_dict()
    reference = tiny.policy.state_dict()
    assert all(torch.equal(reference[k], again[k]) for k in reference)
    assert not all(torch.equal(reference[k], other[k]) for k in reference)


def test_projector_graft_trains_only_the_projector(tiny):
    projector = torch.nn.Linear(3, tiny.info.lm_width)
    calls = []

    def embed(image):  # (B, 3, 64, 64) -> (B, 16, lm_width): pooled pixels through the projector
        calls.append(image.shape)
        grid = F.adaptive_avg_pool2d(image, tiny.info.native_grid)
        return projector(grid.flatten(2).transpose(1, 2))

    batch = tiny.preprocess(make_raw())
    noise, flow_time = fixed_noise_time(tiny, 2)
    with tiny.image_embedder(embed):
        loss = tiny.loss(batch, noise, flow_time)
    loss.mean().backward()
    assert len(calls) == len(CAMERAS) and calls[0] == (2, 3, 64, 64)
    assert projector.weight.grad is not None and projector.weight.grad.abs().sum() > 0
    assert all(p.grad is None and not p.requires_grad for p in tiny.policy.parameters())
    assert "embed_image" not in vars(tiny.policy.model.paligemma_with_expert)
    assert "embed_image" not in dict(tiny.policy.named_modules())


def test_image_embedder_restores_on_exception(tiny):
    owner = tiny.policy.model.paligemma_with_expert
    with pytest.raises(ZeroDivisionError):
        with tiny.image_embedder(lambda image: image):
            assert owner.embed_image is not type(owner).embed_image
            1 / 0
    assert "embed_image" not in vars(owner)


def test_loss_matches_lerobot_own_loss_without_padding(tiny, monkeypatch):
    batch = tiny.preprocess(make_raw())
    noise, flow_time = fixed_noise_time(tiny, 2)
    monkeypatch.setattr(tiny.policy.model, "sample_noise", lambda shape, device: noise)
    monkeypatch.setattr(tiny.policy.model, "sample_time", lambda size, device: flow_time)
    theirs, _ = tiny.policy.forward(batch, reduction="none")
    assert torch.allclose(tiny.loss(batch, noise, flow_time), theirs, rtol=1e-6, atol=1e-7)


def test_loss_ignores_padded_steps(tiny):
    raw = make_raw()
    raw["action_is_pad"][0, 7:] = True
    noise, flow_time = fixed_noise_time(tiny, 2)
    reference = tiny.loss(tiny.preprocess(raw), noise, flow_time)

    padded_changed = {**raw, "action": raw["action"].clone()}
    padded_changed["action"][0, 7:] += 5.0
    assert torch.equal(tiny.loss(tiny.preprocess(padded_changed), noise, flow_time), reference)

    real_changed = {**raw, "action": raw["action"].clone()}
    real_changed["action"][0, 3] += 0.5
    changed = tiny.loss(tiny.preprocess(real_changed), noise, flow_time)
    assert not torch.isclose(changed[0], reference[0])


def test_sample_actions_deterministic_for_fixed_noise(tiny):
    batch = tiny.preprocess(make_raw())
    noise, _ = fixed_noise_time(tiny, 2)
    first = tiny.sample_actions(batch, noise)
    assert first.shape == (2, CHUNK, ACTION_DIM)
    assert torch.equal(first, tiny.sample_actions(batch, noise.clone()))
    assert not torch.equal(first, tiny.sample_actions(batch, noise + 1.0))


def test_sample_time_follows_pi05_beta(tiny):
    draw = lambda seed: tiny.sample_time(20_000, torch.Generator().manual_seed(seed))  # noqa: E731
    times = draw(0)
    assert torch.equal(times, draw(0)) and not torch.equal(times, draw(1))
    assert times.min() >= 0.001 and times.max() <= 1.0
    # Beta(1.5, 1) has mean 0.6; scaled by 0.999 and shifted by 0.001.
    assert abs(times.mean().item() - (0.6 * 0.999 + 0.001)) < 0.01


def test_action_normalisation_is_the_quantile_map(tiny):
    q01, q99 = (torch.tensor(make_stats()["action"][k], dtype=torch.float32) for k in ("q01", "q99"))
    raw = torch.stack([q01, q99, (q01 + q99) / 2])[None]  # (1, 3, 7)
    normalised = tiny.normalize_actions(raw)
    expected = torch.tensor([-1.0, 1.0, 0.0])[None, :, None].expand_as(raw)
    assert torch.allclose(normalised, expected, atol=1e-6)
    assert torch.allclose(tiny.unnormalize_actions(normalised), raw, atol=1e-6)


def test_native_tower_grid_is_siglip_before_the_projector(tiny):
    image = torch.rand(2, 3, 64, 64) * 2 - 1
    grid = tiny.native_tower_grid(image)
    assert grid.shape == (2, 32, 4, 4)
    paligemma = tiny.policy.model.paligemma_with_expert.paligemma.model
    projected = paligemma.multi_modal_projector(grid.flatten(2).transpose(1, 2))
    embedded = tiny.policy.model.paligemma_with_expert.embed_image(image)
    assert torch.allclose(projected, embedded, atol=1e-6)


def test_save_load_round_trip_is_bit_identical(tiny, tmp_path, monkeypatch):
    pi05.save_pretrained(tiny, tmp_path / "tiny_pi05")
    # The saved folder must be self-contained: no tokenizer from the cache.
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "empty_cache"))
    loaded = pi05.load_policy(str(tmp_path / "tiny_pi05"))
    loaded.freeze()
    ours, theirs = tiny.policy.state_dict(), loaded.policy.state_dict()
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
    assert loaded.info == tiny.info and loaded.camera_keys == tiny.camera_keys

    raw = make_raw()
    raw["action_is_pad"][1, 8:] = True
    batch, batch_loaded = tiny.preprocess(raw), loaded.preprocess(raw)
    for key, value in batch.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, batch_loaded[key]), key
    noise, flow_time = fixed_noise_time(tiny, 2)
    assert torch.equal(tiny.sample_actions(batch, noise), loaded.sample_actions(batch_loaded, noise))
    assert torch.equal(tiny.loss(batch, noise, flow_time), loaded.loss(batch_loaded, noise, flow_time))
    actions = torch.randn(2, CHUNK, ACTION_DIM)
    assert torch.equal(tiny.unnormalize_actions(actions), loaded.unnormalize_actions(actions))

    wider = make_stats()
    wider["action"]["q99"] = wider["action"]["q99"] * 3  # caller stats replace the saved ones
    restated = pi05.load_policy(str(tmp_path / "tiny_pi05"), stats=wider)
    q99 = torch.tensor(wider["action"]["q99"], dtype=torch.float32)[None, None]
    assert torch.allclose(restated.normalize_actions(q99), torch.ones_like(q99))


def test_missing_hub_repo_offline_fails_fast(monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    repo_id = "graftbench-absent/pi05_never_downloaded"
    start = time.perf_counter()
    with pytest.raises(BackboneUnavailable) as excinfo:
        pi05.load_policy(repo_id)
    assert time.perf_counter() - start < 2.0
    message = str(excinfo.value)
    assert repo_id in message and str(constants.HF_HUB_CACHE) in message and "\n" not in message


def test_missing_local_folder_is_not_mistaken_for_a_repo(tmp_path):
    with pytest.raises(FileNotFoundError, match="no pi0.5 checkpoint folder"):
        pi05.load_policy(str(tmp_path / "absent" / "tiny_pi05"))


def test_libero_view_of_pi05_base_config():
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    base_cameras = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
    inputs = {
        f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, 224, 224)) for c in base_cameras
    }
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (32,))
    config = PI05Config(
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (32,))},
        device="cpu",
    )
    rename_map, camera_keys = paligemma_load.adapt_real_config(config, make_stats(), pi05.FAMILY)
    assert camera_keys == CAMERAS
    assert [rename_map[k] for k in CAMERAS] == list(config.image_features)
    assert "observation.images.right_wrist_0_rgb" not in config.input_features
    assert config.output_features["action"].shape == (ACTION_DIM,)


def test_dropping_an_unfed_camera_equals_lerobots_masked_empty_camera(tiny):
    # Why adapt_real_config may drop pi05_base's unmapped camera: LeRobot would feed it as a
    # masked -1 image; same weights without that camera give bit-identical actions and losses.
    cameras = (*CAMERAS, "observation.images.right_wrist")
    with_empty = pi05.build_tiny_policy(make_stats(), cameras, chunk_size=CHUNK, seed=0)
    with_empty.freeze()
    raw = make_raw()
    noise, flow_time = fixed_noise_time(tiny, 2)
    batch, batch_empty = tiny.preprocess(raw), with_empty.preprocess(raw)
    assert torch.equal(tiny.sample_actions(batch, noise), with_empty.sample_actions(batch_empty, noise))
    loss_empty = with_empty.loss(batch_empty, noise, flow_time)
    assert torch.equal(tiny.loss(batch, noise, flow_time), loss_empty)


def test_check_real_shapes_gives_pi05_base_geometry():
    shapes = pi05.check_real_shapes()
    assert shapes == {"tokens_per_camera": 256, "lm_width": 2048}
    rows, cols = pi05.INFO_REAL.native_grid
    assert rows * cols == shapes["tokens_per_camera"] and pi05.INFO_REAL.lm_width == shapes["lm_width"]


def test_patches_are_scoped_and_pinned(monkeypatch):
    import lerobot
    from lerobot.policies.pi05 import modeling_pi05

    original = modeling_pi05.get_gemma_config
    with pytest.raises(KeyError):
        with tiny_pi05_patches(TinyPI05Arch()):
            assert modeling_pi05.get_gemma_config("gemma_2b").width == TinyPI05Arch().vlm_width
            raise KeyError("inside")
    assert modeling_pi05.get_gemma_config is original
    assert modeling_pi05.get_gemma_config("gemma_2b").width == 2048
    monkeypatch.setattr(lerobot, "__version__", "0.7.0")
    with pytest.raises(RuntimeError, match="0.6.1"):
        pi05.build_tiny_policy(make_stats())


def test_stats_without_quantiles_are_rejected():
    stats = make_stats()
    del stats["action"]["q99"]
    with pytest.raises(ValueError, match="q99"):
        pi05.build_tiny_policy(stats)
