"""backbones.pi0 on the tiny, offline pi0 (a real LeRobot PI0Policy with tiny sizes).

What pi0 shares with pi0.5 (backbones.paligemma) is tested again here on pi0's own model; what is
pi0's own is tested first: the state as a continuous token, MEAN_STD normalisation.
"""

from __future__ import annotations

import json
import time

import pytest
import torch
import torch.nn.functional as F

from backbones import paligemma_load, pi0, pi05
from backbones.base import BackboneUnavailable
# The tiny PaliGemma test data (cameras, stats with mean/std AND quantiles, raw batches) is pi0.5's.
from tests.test_backbone_pi05 import (
    ACTION_DIM, CAMERAS, CHUNK, STATE_DIM, fixed_noise_time, make_raw, make_stats,
)


@pytest.fixture(scope="module")
def tiny():
    backbone = pi0.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0)
    backbone.freeze()
    return backbone


def test_tiny_build_is_a_small_real_pi0(tiny):
    from lerobot.policies.pi0.modeling_pi0 import PI0Policy

    assert isinstance(tiny.policy, PI0Policy)
    assert sum(p.numel() for p in tiny.policy.parameters()) < 5_000_000
    assert tiny.info.name == "pi0" and tiny.info.native_grid == (4, 4) and tiny.info.lm_width == 64
    assert (tiny.info.chunk_size, tiny.info.max_action_dim, tiny.info.num_denoise_steps) == (10, 32, 10)
    assert tiny.camera_keys == CAMERAS and tuple(tiny.policy.config.image_features) == CAMERAS
    assert tiny.policy.model.state_proj.in_features == tiny.policy.config.max_state_dim == 32
    q = tiny.language_model().layers[0].self_attn
    assert hasattr(q, "q_proj") and hasattr(q, "v_proj")


# -- pi0's own: the state is a continuous token, not prompt text --------------------------------
def test_state_enters_as_a_token_not_as_prompt_text(tiny):
    raw = make_raw()
    other = {**raw, "observation.state": raw["observation.state"] + 1.0}
    batch, batch_other = tiny.preprocess(raw), tiny.preprocess(other)
    assert batch["task"][0] == "pick up the red block and place it on the plate\n"  # no "State:"
    assert torch.equal(batch["observation.language.tokens"], batch_other["observation.language.tokens"])
    noise, flow_time = fixed_noise_time(tiny, 2)
    assert not torch.allclose(tiny.loss(batch, noise, flow_time), tiny.loss(batch_other, noise, flow_time))
    assert not torch.allclose(tiny.sample_actions(batch, noise), tiny.sample_actions(batch_other, noise))


def test_loss_matches_lerobot_own_loss_without_padding(tiny, monkeypatch):
    # LeRobot's own PI0Policy.forward pads and passes the state itself: equal only if ours does too.
    batch = tiny.preprocess(make_raw())
    noise, flow_time = fixed_noise_time(tiny, 2)
    monkeypatch.setattr(tiny.policy.model, "sample_noise", lambda shape, device: noise)
    monkeypatch.setattr(tiny.policy.model, "sample_time", lambda size, device: flow_time)
    theirs, _ = tiny.policy.forward(batch, reduction="none")
    assert torch.allclose(tiny.loss(batch, noise, flow_time), theirs, rtol=1e-6, atol=1e-7)


def test_sampler_matches_lerobot_own_sampler(tiny):
    batch = tiny.preprocess(make_raw())
    noise, _ = fixed_noise_time(tiny, 2)
    images, img_masks = tiny.policy._preprocess_images(batch)
    theirs = tiny.policy.model.sample_actions(
        images, img_masks, batch["observation.language.tokens"],
        batch["observation.language.attention_mask"], tiny.policy.prepare_state(batch), noise=noise,
    )[:, :, :ACTION_DIM]
    assert torch.equal(tiny.sample_actions(batch, noise), theirs)


def test_action_and_state_normalisation_is_mean_std(tiny):
    stats = make_stats()
    mean, std = (torch.tensor(stats["action"][k], dtype=torch.float32) for k in ("mean", "std"))
    raw = torch.stack([mean, mean + std, mean - 2 * std])[None]  # (1, 3, 7)
    normalised = tiny.normalize_actions(raw)
    expected = torch.tensor([0.0, 1.0, -2.0])[None, :, None].expand_as(raw)
    assert torch.allclose(normalised, expected, atol=1e-5)
    assert torch.allclose(tiny.unnormalize_actions(normalised), raw, atol=1e-6)
    state_mean, state_std = (torch.tensor(stats["observation.state"][k], dtype=torch.float32)
                             for k in ("mean", "std"))
    raw_batch = make_raw()
    raw_batch["observation.state"] = (state_mean + state_std).expand(2, STATE_DIM).clone()
    normalised_state = tiny.preprocess(raw_batch)["observation.state"]
    assert torch.allclose(normalised_state, torch.ones(2, STATE_DIM), atol=1e-5)


def test_stats_need_mean_and_std_not_quantiles():
    without_quantiles = make_stats()
    for key in without_quantiles:
        del without_quantiles[key]["q01"], without_quantiles[key]["q99"]
    pi0.build_tiny_policy(without_quantiles)  # pi0 does not read them
    without_std = make_stats()
    del without_std["observation.state"]["std"]
    with pytest.raises(ValueError, match=r"'std'.*MEAN_STD"):
        pi0.build_tiny_policy(without_std)


def test_check_real_shapes_gives_pi0_base_geometry():
    shapes = pi0.check_real_shapes()
    assert shapes == {"tokens_per_camera": 256, "lm_width": 2048}
    rows, cols = pi0.INFO_REAL.native_grid
    assert rows * cols == shapes["tokens_per_camera"] and pi0.INFO_REAL.lm_width == shapes["lm_width"]


# -- the graft hook ---------------------------------------------------------------------------
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


def test_grafted_embedder_is_what_the_sampler_sees(tiny):
    # A no-op hook would leave the native tower in place: zero image tokens must change actions.
    batch = tiny.preprocess(make_raw())
    noise, _ = fixed_noise_time(tiny, 2)
    native = tiny.sample_actions(batch, noise)
    zeros = lambda image: torch.zeros(image.shape[0], 16, tiny.info.lm_width)  # noqa: E731
    with tiny.image_embedder(zeros):
        grafted = tiny.sample_actions(batch, noise)
        other = {**make_raw(seed=5), "observation.state": make_raw()["observation.state"]}
        assert torch.equal(grafted, tiny.sample_actions(tiny.preprocess(other), noise))  # images unused
    assert not torch.allclose(native, grafted)
    assert torch.equal(native, tiny.sample_actions(batch, noise))  # restored


def test_image_embedder_restores_on_exception(tiny):
    owner = tiny.policy.model.paligemma_with_expert
    with pytest.raises(ZeroDivisionError):
        with tiny.image_embedder(lambda image: image):
            assert owner.embed_image is not type(owner).embed_image
            1 / 0
    assert "embed_image" not in vars(owner)


def test_native_tower_grid_is_siglip_before_the_projector(tiny):
    image = torch.rand(2, 3, 64, 64) * 2 - 1
    grid = tiny.native_tower_grid(image)
    assert grid.shape == (2, 32, 4, 4)
    paligemma = tiny.policy.model.paligemma_with_expert.paligemma.model
    projected = paligemma.multi_modal_projector(grid.flatten(2).transpose(1, 2))
    embedded = tiny.policy.model.paligemma_with_expert.embed_image(image)
    assert torch.allclose(projected, embedded, atol=1e-6)


# -- loss and sampler -------------------------------------------------------------------------
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
    assert not torch.isclose(tiny.loss(tiny.preprocess(real_changed), noise, flow_time)[0], reference[0])


def test_sample_actions_deterministic_for_fixed_noise(tiny):
    batch = tiny.preprocess(make_raw())
    noise, _ = fixed_noise_time(tiny, 2)
    first = tiny.sample_actions(batch, noise)
    assert first.shape == (2, CHUNK, ACTION_DIM)
    assert torch.equal(first, tiny.sample_actions(batch, noise.clone()))
    assert not torch.equal(first, tiny.sample_actions(batch, noise + 1.0))


def test_sample_time_follows_pi0_beta(tiny):
    times = tiny.sample_time(20_000, torch.Generator().manual_seed(0))
    assert times.min() >= 0.001 and times.max() <= 1.0
    assert abs(times.mean().item() - (0.6 * 0.999 + 0.001)) < 0.01  # Beta(1.5, 1), scaled, shifted


# -- building, saving, loading ----------------------------------------------------------------
def test_tiny_build_is_deterministic_from_seed(tiny):
    again = pi0.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0).policy.state_dict()
    other = pi0.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=1).policy.state_dict()
    reference = tiny.policy.state_dict()
    assert all(torch.equal(reference[k], again[k]) for k in reference)
    assert not all(torch.equal(reference[k], other[k]) for k in reference)


def test_save_load_round_trip_is_bit_identical(tiny, tmp_path, monkeypatch):
    pi0.save_pretrained(tiny, tmp_path / "tiny_pi0")
    assert (tmp_path / "tiny_pi0" / pi0.MARKER_FILE).is_file()
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "empty_cache"))  # self-contained folder
    loaded = pi0.load_policy(str(tmp_path / "tiny_pi0"))
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

    wider = make_stats()
    wider["action"]["std"] = wider["action"]["std"] * 3  # caller stats replace the saved ones
    restated = pi0.load_policy(str(tmp_path / "tiny_pi0"), stats=wider)
    std = torch.tensor(wider["action"]["std"], dtype=torch.float32)[None, None]
    assert torch.allclose(restated.normalize_actions(std), torch.ones_like(std), atol=1e-5)


def test_a_checkpoint_of_another_type_or_on_relative_actions_is_refused(tiny, tmp_path):
    pi05_tiny = pi05.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0)
    pi05.save_pretrained(pi05_tiny, tmp_path / "a_pi05")
    with pytest.raises(ValueError, match="'pi05' checkpoint, not 'pi0'"):
        pi0.load_policy(str(tmp_path / "a_pi05"))

    pi0.save_pretrained(tiny, tmp_path / "relative")
    config = tmp_path / "relative" / "config.json"
    config.write_text(json.dumps({**json.loads(config.read_text()), "use_relative_actions": True}))
    with pytest.raises(ValueError, match="use_relative_actions"):
        pi0.load_policy(str(tmp_path / "relative"))


def test_missing_hub_repo_offline_fails_fast(monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    repo_id = "graftbench-absent/pi0_never_downloaded"
    start = time.perf_counter()
    with pytest.raises(BackboneUnavailable) as excinfo:
        pi0.load_policy(repo_id)
    assert time.perf_counter() - start < 2.0
    message = str(excinfo.value)
    assert repo_id in message and str(constants.HF_HUB_CACHE) in message and "\n" not in message


def test_missing_local_folder_is_not_mistaken_for_a_repo(tmp_path):
    with pytest.raises(FileNotFoundError, match="no pi0 checkpoint folder"):
        pi0.load_policy(str(tmp_path / "absent" / "tiny_pi0"))


def test_libero_view_of_pi0_base_config():
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.pi0.configuration_pi0 import PI0Config

    base_cameras = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
    inputs = {
        f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, 224, 224)) for c in base_cameras
    }
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (32,))
    config = PI0Config(
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (32,))},
        device="cpu",
    )
    rename_map, camera_keys = paligemma_load.adapt_real_config(config, make_stats(), pi0.FAMILY)
    assert camera_keys == CAMERAS
    assert [rename_map[k] for k in CAMERAS] == list(config.image_features)
    assert "observation.images.right_wrist_0_rgb" not in config.input_features
    assert config.input_features["observation.state"].shape == (STATE_DIM,)
    assert config.output_features["action"].shape == (ACTION_DIM,)


def test_dropping_an_unfed_camera_equals_lerobots_masked_empty_camera(tiny):
    # As for pi0.5: a masked -1 camera neither attends nor shifts the positions of the state token.
    cameras = (*CAMERAS, "observation.images.right_wrist")
    with_empty = pi0.build_tiny_policy(make_stats(), cameras, chunk_size=CHUNK, seed=0)
    with_empty.freeze()
    raw = make_raw()
    noise, flow_time = fixed_noise_time(tiny, 2)
    batch, batch_empty = tiny.preprocess(raw), with_empty.preprocess(raw)
    assert torch.equal(tiny.sample_actions(batch, noise), with_empty.sample_actions(batch_empty, noise))
    assert torch.equal(tiny.loss(batch, noise, flow_time), with_empty.loss(batch_empty, noise, flow_time))
