"""SmolVLA's own (backbones.smolvla), on the tiny SmolVLA (a real SmolVLAPolicy on a tiny SmolVLM):
its tokenizer, its masked-mean loss, LeRobot's time draw, the width check, smolvla_base's camera
layout, a hub id from the HF cache. The adapter contract: tests/test_backbone_contract.py."""

from __future__ import annotations

import pytest
import torch

from backbones import smolvla
from tests.backbone_data import (
    ACTION_DIM, CAMERAS, CHUNK, build_tiny, fixed_noise_time, make_raw, make_stats,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny():
    return build_tiny(smolvla)


def test_tiny_build_is_a_small_real_smolvla(tiny):
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    assert isinstance(tiny.policy, SmolVLAPolicy)
    assert sum(p.numel() for p in tiny.policy.parameters()) < 1_000_000
    # 64 px, patch 16 -> 4x4 patches, pixel shuffle 2 -> 2x2 tokens; LM width 64.
    assert tiny.info.native_grid == (2, 2) and tiny.info.lm_width == 64
    assert tuple(tiny.policy.config.image_features) == CAMERAS


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


def test_image_embedder_checks_the_token_width(tiny):
    owner = tiny.policy.model.vlm_with_expert
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


def test_sample_actions_keeps_the_mode_and_checks_the_noise(tiny):
    batch = tiny.preprocess(make_raw())
    noise, _ = fixed_noise_time(tiny, 2)
    tiny.policy.train()  # sample_actions must not leave the policy in another mode
    first = tiny.sample_actions(batch, noise)
    assert tiny.policy.training
    tiny.policy.eval()
    assert torch.equal(first, tiny.sample_actions(batch, noise))  # dropout off either way
    with pytest.raises(ValueError, match="noise has shape"):
        tiny.sample_actions(batch, noise[:, :, :ACTION_DIM])


def test_sample_time_reproduces_smolvlas_own_draw(tiny):
    from scipy.stats import ks_2samp

    times = tiny.sample_time(4000, torch.Generator().manual_seed(0))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        theirs = tiny.policy.model.sample_time(4000, "cpu")
    assert ks_2samp(times.numpy(), theirs.numpy()).pvalue > 1e-3


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


def test_check_real_shapes_gives_smolvla_base_geometry():
    shapes = smolvla.check_real_shapes()
    assert shapes["tokens_per_camera"] == 64 and shapes["lm_width"] == 960
    assert shapes["tower_tokens"] == 32 * 32 and shapes["tower_width"] == 768
    assert shapes["native_grid"] == smolvla.INFO_REAL.native_grid == (8, 8)
    assert 440e6 < shapes["parameters"] < 460e6  # "SmolVLA-450M"
