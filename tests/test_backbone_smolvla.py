"""backbones.smolvla on the tiny, offline SmolVLA (a real LeRobot SmolVLAPolicy on a tiny SmolVLM)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from backbones import smolvla
from backbones.base import BackboneUnavailable

CAMERAS = ("observation.images.image", "observation.images.wrist_image")
CHUNK, STATE_DIM, ACTION_DIM = 10, 8, 7


def make_stats(state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM, cameras=CAMERAS) -> dict:
    def one(dim: int, scale: float) -> dict:
        spread = np.linspace(0.5, 2.0, dim) * scale
        return {
            "mean": np.linspace(-0.2, 0.3, dim), "std": spread / 2, "min": -spread * 1.5,
            "max": spread * 1.5, "q01": -spread, "q99": spread,
        }
    stats = {"observation.state": one(state_dim, 1.0), "action": one(action_dim, 0.5)}
    for camera in cameras:  # present, as in LeRobot datasets; SmolVLA's VISUAL mode is IDENTITY
        stats[camera] = {"mean": np.full((3, 1, 1), 0.5), "std": np.full((3, 1, 1), 0.25)}
    return stats


def make_raw(batch: int = 2, seed: int = 0, cameras=CAMERAS) -> dict:
    g = torch.Generator().manual_seed(seed)
    raw = {key: torch.rand(batch, 3, 64, 64, generator=g) for key in cameras}
    raw["observation.state"] = torch.randn(batch, STATE_DIM, generator=g)
    raw["action"] = torch.randn(batch, CHUNK, ACTION_DIM, generator=g) * 0.3
    raw["action_is_pad"] = torch.zeros(batch, CHUNK, dtype=torch.bool)
    raw["task"] = ["pick up the red block and place it on the plate", "open the top drawer"][:batch]
    return raw


def fixed_noise_time(backbone, batch: int, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(batch, CHUNK, backbone.info.max_action_dim, generator=g)
    return noise, backbone.sample_time(batch, g)


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    # Tiny ops are all thread overhead: with the 2 cores shared, a 10-step sample took 1.3 s on
    # 2 threads and 0.1 s on 1. Restored afterwards for the other test modules.
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def tiny():
    backbone = smolvla.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0)
    backbone.freeze()
    return backbone


def test_tiny_build_is_a_small_real_smolvla(tiny):
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    assert isinstance(tiny.policy, SmolVLAPolicy)
    assert sum(p.numel() for p in tiny.policy.parameters()) < 1_000_000
    # 64 px, patch 16 -> 4x4 patches, pixel shuffle 2 -> 2x2 tokens; LM width 64.
    assert tiny.info.native_grid == (2, 2) and tiny.info.lm_width == 64
    assert (tiny.info.chunk_size, tiny.info.max_action_dim, tiny.info.num_denoise_steps) == (10, 32, 10)
    assert tiny.camera_keys == CAMERAS and tuple(tiny.policy.config.image_features) == CAMERAS
    attention = tiny.language_model().layers[0].self_attn
    assert hasattr(attention, "q_proj") and hasattr(attention, "v_proj")


def test_tiny_tokenizer_knows_every_task_word(tiny):
    batch = tiny.preprocess(make_raw())
    (step,) = [s for s in tiny.preprocessor.steps if type(s).__name__ == "TokenizerProcessorStep"]
    unk = step.input_tokenizer.convert_tokens_to_ids("[UNK]")
    tokens, mask = batch["observation.language.tokens"], batch["observation.language.attention_mask"]
    assert batch["task"][0] == "pick up the red block and place it on the plate\n"
    assert mask[0].sum() == 11 and mask[1].sum() == 4  # words + final "." / padding to longest
    assert not (tokens[mask] == unk).any()
    assert (step.input_tokenizer("Pick up the ZEBRA.")["input_ids"][3]) == unk
    from bench.suites.synthetic import OBJECT_TASKS, SPATIAL_TASKS

    spatial = [f"pick up the {c} block and place it {'on' if d == 'plate' else 'in'} the {d}"
               for c, d in SPATIAL_TASKS]
    for task in [*spatial, *OBJECT_TASKS, "put both moka pots on the stove",
                 "pick up the black bowl between the plate and the ramekin and place it on the plate"]:
        assert unk not in step.input_tokenizer(task)["input_ids"], task


def test_tiny_build_is_deterministic_from_seed(tiny):
    again = smolvla.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0).policy.state_dict()
    other = smolvla.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=1).policy.state_dict()
    reference = tiny.policy.state_dict()
    assert all(torch.equal(reference[k], again[k]) for k in reference)
    assert not all(torch.equal(reference[k], other[k]) for k in reference)


def test_projector_graft_trains_only_the_projector(tiny):
    projector = torch.nn.Linear(3, tiny.info.lm_width)
    calls = []

    def embed(image):  # (B, 3, 64, 64) in [-1, 1] -> (B, 4, lm_width): pooled pixels, projected
        calls.append((tuple(image.shape), image.min().item() >= -1.0))
        grid = F.adaptive_avg_pool2d(image, tiny.info.native_grid)
        return projector(grid.flatten(2).transpose(1, 2))

    batch = tiny.preprocess(make_raw())
    noise, flow_time = fixed_noise_time(tiny, 2)
    with tiny.image_embedder(embed):
        loss = tiny.loss(batch, noise, flow_time)
    loss.mean().backward()
    assert calls == [((2, 3, 64, 64), True)] * len(CAMERAS)
    assert projector.weight.grad is not None and projector.weight.grad.abs().sum() > 0
    assert all(p.grad is None and not p.requires_grad for p in tiny.policy.parameters())
    assert "embed_image" not in vars(tiny.policy.model.vlm_with_expert)


def test_image_embedder_restores_on_exception_and_checks_width(tiny):
    owner = tiny.policy.model.vlm_with_expert
    with pytest.raises(ZeroDivisionError):
        with tiny.image_embedder(lambda image: image):
            assert "embed_image" in vars(owner)
            1 / 0
    assert "embed_image" not in vars(owner)
    batch = tiny.preprocess(make_raw())
    noise, flow_time = fixed_noise_time(tiny, 2)
    with pytest.raises(ValueError, match="needs \\(2, N_tokens, 64\\)"):
        with tiny.image_embedder(lambda image: torch.zeros(2, 4, 65)):
            tiny.loss(batch, noise, flow_time)
    assert "embed_image" not in vars(owner)


def test_native_tower_grid_is_the_tower_before_the_connector(tiny):
    image = torch.rand(2, 3, 64, 64) * 2 - 1
    grid = tiny.native_tower_grid(image)
    assert grid.shape == (2, 32, 4, 4)  # vision width 32 on a 4x4 patch grid
    connector = tiny.policy.model.vlm_with_expert.get_vlm_model().connector
    from_grid = connector(grid.flatten(2).transpose(1, 2))
    assert torch.allclose(from_grid, tiny.policy.model.vlm_with_expert.embed_image(image), atol=1e-6)


def test_loss_is_the_masked_mean_of_lerobots_per_element_loss(tiny):
    raw = make_raw()
    raw["action_is_pad"][1, 6:] = True
    batch = tiny.preprocess(raw)
    noise, flow_time = fixed_noise_time(tiny, 2)
    policy = tiny.policy
    images, masks = policy.prepare_images(batch)
    elementwise = policy.model.forward(
        images, masks, batch["observation.language.tokens"],
        batch["observation.language.attention_mask"], policy.prepare_state(batch),
        policy.prepare_action(batch), noise, flow_time,
    )  # (B, chunk, 32)
    valid = (~raw["action_is_pad"]).float()[:, :, None]
    expected = (elementwise[:, :, :ACTION_DIM] * valid).sum((1, 2)) / (valid.sum((1, 2)) * ACTION_DIM)
    assert torch.allclose(tiny.loss(batch, noise, flow_time), expected, rtol=1e-6, atol=1e-7)


def test_loss_ignores_padded_tail_steps(tiny):
    # SmolVLA's action tokens attend causally (embed_suffix att_masks all 1), so a padded tail
    # cannot reach the real steps: the loss is bit-identical whatever the padded actions are.
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
    tiny.policy.train()  # sample_actions must not leave the policy in another mode
    first = tiny.sample_actions(batch, noise)
    assert tiny.policy.training
    tiny.policy.eval()
    assert first.shape == (2, CHUNK, ACTION_DIM)
    assert torch.equal(first, tiny.sample_actions(batch, noise.clone()))
    assert not torch.equal(first, tiny.sample_actions(batch, noise + 1.0))
    with pytest.raises(ValueError, match="noise has shape"):
        tiny.sample_actions(batch, noise[:, :, :ACTION_DIM])


def test_sample_time_reproduces_smolvlas_beta(tiny):
    from scipy.stats import ks_2samp

    draw = lambda seed: tiny.sample_time(4000, torch.Generator().manual_seed(seed))  # noqa: E731
    times = draw(0)
    assert torch.equal(times, draw(0)) and not torch.equal(times, draw(1))
    assert times.min() >= 0.001 and times.max() <= 1.0
    assert abs(times.mean().item() - (0.6 * 0.999 + 0.001)) < 0.01  # Beta(1.5, 1) mean 0.6
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        theirs = tiny.policy.model.sample_time(4000, "cpu")
    assert ks_2samp(times.numpy(), theirs.numpy()).pvalue > 1e-3


def test_action_normalisation_is_lerobots_mean_std(tiny):
    stats = make_stats()["action"]
    mean, std = (torch.tensor(stats[k], dtype=torch.float32) for k in ("mean", "std"))
    raw = torch.stack([mean, mean + std, mean - 2 * std])[None]  # (1, 3, 7)
    normalised = tiny.normalize_actions(raw)
    expected = torch.tensor([0.0, 1.0, -2.0])[None, :, None].expand_as(raw)
    assert torch.allclose(normalised, expected, atol=1e-5)
    assert torch.allclose(tiny.unnormalize_actions(normalised), raw, atol=1e-6)


def test_save_load_round_trip_is_bit_identical(tiny, tmp_path, monkeypatch):
    smolvla.save_pretrained(tiny, tmp_path / "tiny_smolvla")
    # The saved folder must be self-contained: its SmolVLM folder travels with it.
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "empty_cache"))
    loaded = smolvla.load_policy(str(tmp_path / "tiny_smolvla"))
    loaded.freeze()
    ours, theirs = tiny.policy.state_dict(), loaded.policy.state_dict()
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
    assert loaded.info == tiny.info and loaded.camera_keys == tiny.camera_keys
    assert loaded.policy.config.vlm_model_name == str(tmp_path / "tiny_smolvla" / "smolvlm")

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

    shifted = make_stats()
    shifted["action"]["mean"] = shifted["action"]["mean"] + 1.0  # caller stats replace the saved ones
    restated = smolvla.load_policy(str(tmp_path / "tiny_smolvla"), stats=shifted)
    mean = torch.tensor(shifted["action"]["mean"], dtype=torch.float32)[None, None]
    assert torch.allclose(restated.normalize_actions(mean), torch.zeros_like(mean), atol=1e-6)


def test_smolvla_base_layout_is_fitted_to_libero(tmp_path):
    # A checkpoint shaped like smolvla_base (cameras camera1/2/3, 6-dim state and action).
    base_cameras = tuple(f"observation.images.camera{i}" for i in (1, 2, 3))
    base = smolvla.build_tiny_policy(make_stats(6, 6, base_cameras), base_cameras, state_dim=6,
                                     action_dim=6, chunk_size=CHUNK, seed=0)
    smolvla.save_pretrained(base, tmp_path / "base_like")
    with pytest.raises(ValueError, match="pass stats="):
        smolvla.load_policy(str(tmp_path / "base_like"))
    fitted = smolvla.load_policy(str(tmp_path / "base_like"), stats=make_stats())
    assert fitted.camera_keys == CAMERAS and fitted.rename_map == smolvla.SMOLVLA_BASE_RENAME
    assert tuple(fitted.policy.config.image_features) == base_cameras[:2]  # camera3 dropped
    assert fitted.policy.config.action_feature.shape == (ACTION_DIM,)
    ours, theirs = base.policy.state_dict(), fitted.policy.state_dict()
    assert all(torch.equal(ours[k], theirs[k]) for k in ours)
    batch = fitted.preprocess(make_raw())
    assert fitted.sample_actions(batch, fixed_noise_time(fitted, 2)[0]).shape == (2, CHUNK, ACTION_DIM)
    with pytest.raises(KeyError, match="lacks camera"):
        fitted.preprocess({k: v for k, v in make_raw().items() if k != CAMERAS[1]})


def test_hub_repo_in_the_hf_cache_loads_offline(tiny, tmp_path, monkeypatch):
    # The real-world path (a hub id resolved from the HF cache), on a hand-made cache entry.
    from huggingface_hub import constants

    repo_id, commit = "graftbench-test/tiny_smolvla", "0" * 40
    entry = tmp_path / "hub" / "models--graftbench-test--tiny_smolvla"
    smolvla.save_pretrained(tiny, entry / "snapshots" / commit)
    (entry / "refs").mkdir()
    (entry / "refs" / "main").write_text(commit)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    loaded = smolvla.load_policy(repo_id)
    ours, theirs = tiny.policy.state_dict(), loaded.policy.state_dict()
    assert all(torch.equal(ours[k], theirs[k]) for k in ours) and loaded.info == tiny.info


def test_missing_hub_repo_offline_fails_fast(monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    repo_id = "graftbench-absent/smolvla_never_downloaded"
    start = time.perf_counter()
    with pytest.raises(BackboneUnavailable) as excinfo:
        smolvla.load_policy(repo_id, stats=make_stats())
    assert time.perf_counter() - start < 2.0
    message = str(excinfo.value)
    assert repo_id in message and str(constants.HF_HUB_CACHE) in message and "\n" not in message
    assert f"hf download {repo_id}" in message


def test_missing_local_folder_is_not_mistaken_for_a_repo(tmp_path):
    with pytest.raises(FileNotFoundError, match="no SmolVLA checkpoint folder"):
        smolvla.load_policy(str(tmp_path / "absent" / "tiny_smolvla"))


def test_check_real_shapes_gives_smolvla_base_geometry():
    shapes = smolvla.check_real_shapes()
    assert shapes["tokens_per_camera"] == 64 and shapes["lm_width"] == 960
    assert shapes["tower_tokens"] == 32 * 32 and shapes["tower_width"] == 768
    assert shapes["native_grid"] == smolvla.INFO_REAL.native_grid == (8, 8)
    assert 440e6 < shapes["parameters"] < 460e6  # "SmolVLA-450M"
