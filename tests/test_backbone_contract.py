"""The adapter contract (backbones.base), once for every backbone family in the registry.

Parametrised over `backbones.BACKBONES` (one family per adapter module): a new backbone gets all
of this by being registered. Each runs on the family's tiny build, a real LeRobot policy with
tiny sizes. What differs between families: tests/test_backbone_<family>.py and, for what pi0 and
pi0.5 share, tests/test_backbone_paligemma.py.
"""

from __future__ import annotations

import tempfile
import time

import pytest
import torch
import torch.nn.functional as F

from backbones.base import BackboneUnavailable
from tests.backbone_data import (
    ACTION_DIM, CAMERAS, CHUNK, FAMILIES, adapter, build_tiny, family_name, fixed_noise_time,
    make_raw, make_stats, policy_type,
)


@pytest.fixture(scope="module", params=FAMILIES, ids=family_name)
def module(request):
    return adapter(request.param)


@pytest.fixture(scope="module")
def tiny(module):
    return build_tiny(module)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def pooled_projector(tiny, calls: list):
    """An image embedder: pixels (B, 3, H, W) pooled to the native grid, one Linear(3 -> width)."""
    projector = torch.nn.Linear(3, tiny.info.lm_width)

    def embed(image):
        calls.append((tuple(image.shape), image.min().item() >= -1.0, image.max().item() <= 1.0))
        grid = F.adaptive_avg_pool2d(image, tiny.info.native_grid)
        return projector(grid.flatten(2).transpose(1, 2))

    return projector, embed


# -- the tiny build ------------------------------------------------------------------------------
def test_tiny_build_is_a_small_real_lerobot_policy(module, tiny):
    kind = policy_type(module.__name__)  # the registry's LeRobot type of this adapter
    assert isinstance(tiny, module.BACKBONE_CLASS) and tiny.policy.config.type == kind
    assert type(tiny.policy).__module__ == f"lerobot.policies.{kind}.modeling_{kind}"
    assert sum(p.numel() for p in tiny.policy.parameters()) < 5_000_000
    assert (tiny.info.chunk_size, tiny.info.max_action_dim, tiny.info.num_denoise_steps) == (10, 32, 10)
    assert tiny.camera_keys == CAMERAS
    attention = tiny.language_model().layers[0].self_attn  # the LoRA control's targets
    assert hasattr(attention, "q_proj") and hasattr(attention, "v_proj")


def test_tiny_build_is_deterministic_from_seed(module, tiny):
    again = build_tiny(module, seed=0).policy.state_dict()
    other = build_tiny(module, seed=1).policy.state_dict()
    reference = tiny.policy.state_dict()
    assert all(torch.equal(reference[k], again[k]) for k in reference)
    assert not all(torch.equal(reference[k], other[k]) for k in reference)


# -- the graft hook ------------------------------------------------------------------------------
def test_projector_graft_trains_only_the_projector(tiny):
    calls: list = []
    projector, embed = pooled_projector(tiny, calls)
    batch = tiny.preprocess(make_raw())
    noise, flow_time = fixed_noise_time(tiny, 2)
    with tiny.image_embedder(embed):
        loss = tiny.loss(batch, noise, flow_time)
    loss.mean().backward()
    # Once per camera, with the image the policy would feed its tower (scaled to [-1, 1]).
    assert [c[0] for c in calls] == [(2, 3, 64, 64)] * len(CAMERAS) and all(c[1] and c[2] for c in calls)
    assert projector.weight.grad is not None and projector.weight.grad.abs().sum() > 0
    assert all(p.grad is None and not p.requires_grad for p in tiny.policy.parameters())
    assert not any(n.startswith("embed_image") for n, _ in tiny.policy.named_parameters())


def test_grafted_embedder_is_what_the_sampler_sees_and_is_restored(tiny):
    # A no-op hook would leave the native tower in place: zero image tokens must change actions,
    # and with them the images no longer matter.
    batch = tiny.preprocess(make_raw())
    noise, _ = fixed_noise_time(tiny, 2)
    native = tiny.sample_actions(batch, noise)
    tokens = tiny.info.native_grid[0] * tiny.info.native_grid[1]
    zeros = lambda image: torch.zeros(image.shape[0], tokens, tiny.info.lm_width)  # noqa: E731
    other_images = {**make_raw(seed=5), "observation.state": make_raw()["observation.state"]}
    with tiny.image_embedder(zeros):
        grafted = tiny.sample_actions(batch, noise)
        assert torch.equal(grafted, tiny.sample_actions(tiny.preprocess(other_images), noise))
    assert not torch.allclose(native, grafted)
    assert torch.equal(native, tiny.sample_actions(batch, noise))  # restored
    with pytest.raises(ZeroDivisionError):
        with tiny.image_embedder(zeros):
            1 / 0
    assert torch.equal(native, tiny.sample_actions(batch, noise))  # restored after an error too


def test_native_tower_grid_is_a_feature_grid_per_image(tiny):
    grid = tiny.native_tower_grid(torch.rand(2, 3, 64, 64) * 2 - 1)
    assert grid.ndim == 4 and grid.shape[0] == 2 and grid.dtype == torch.float32
    assert torch.isfinite(grid).all()


# -- loss and sampler ----------------------------------------------------------------------------
def test_loss_ignores_padded_steps(tiny):
    raw = make_raw()
    raw["action_is_pad"][0, 7:] = True
    noise, flow_time = fixed_noise_time(tiny, 2)
    reference = tiny.loss(tiny.preprocess(raw), noise, flow_time)
    assert reference.shape == (2,)

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


def test_sample_time_is_the_shifted_beta(tiny):
    draw = lambda seed: tiny.sample_time(20_000, torch.Generator().manual_seed(seed))  # noqa: E731
    times = draw(0)
    assert torch.equal(times, draw(0)) and not torch.equal(times, draw(1))
    assert times.min() >= 0.001 and times.max() <= 1.0
    assert abs(times.mean().item() - (0.6 * 0.999 + 0.001)) < 0.01  # Beta(1.5, 1), scaled, shifted


def test_action_normalisation_is_the_map_its_config_names(tiny):
    stats = {k: torch.tensor(v, dtype=torch.float32) for k, v in make_stats()["action"].items()}
    raw = torch.randn(1, 3, ACTION_DIM)
    mode = tiny.policy.config.normalization_mapping["ACTION"].value
    expected = {"MEAN_STD": lambda: (raw - stats["mean"]) / stats["std"],
                "QUANTILES": lambda: 2 * (raw - stats["q01"]) / (stats["q99"] - stats["q01"]) - 1}
    assert mode in expected, f"a new normalisation mode {mode!r}: add its map here"
    normalised = tiny.normalize_actions(raw)
    assert torch.allclose(normalised, expected[mode](), atol=1e-5)
    assert torch.allclose(tiny.unnormalize_actions(normalised), raw, atol=1e-5)


# -- saving, loading, the offline world ----------------------------------------------------------
def test_save_load_round_trip_is_bit_identical(module, tiny, tmp_path, monkeypatch):
    module.save_pretrained(tiny, tmp_path / "tiny")
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "empty_cache"))  # self-contained folder
    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    loaded = module.load_policy(str(tmp_path / "tiny"))
    assert not any((tmp_path / "tmp").iterdir())  # LeRobot's config parse leaves a temp file
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


def test_caller_stats_replace_the_saved_ones(module, tiny, tmp_path):
    module.save_pretrained(tiny, tmp_path / "tiny")
    other = make_stats()
    for key in ("mean", "std", "min", "max", "q01", "q99"):
        other["action"][key] = other["action"][key] * 3 + 0.5
    restated = module.load_policy(str(tmp_path / "tiny"), stats=other)
    built_with_them = build_tiny(module, stats=other)
    actions = torch.randn(1, 3, ACTION_DIM)
    assert torch.allclose(restated.normalize_actions(actions), built_with_them.normalize_actions(actions))
    assert not torch.allclose(restated.normalize_actions(actions), tiny.normalize_actions(actions))


def test_missing_hub_repo_offline_fails_fast_in_one_line(module, tiny, monkeypatch):
    from huggingface_hub import constants  # `tiny`: LeRobot's modules imported before the clock

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    repo_id = f"graftbench-absent/{family_name(module.__name__)}_never_downloaded"
    start = time.perf_counter()
    with pytest.raises(BackboneUnavailable) as excinfo:
        module.load_policy(repo_id, stats=make_stats())
    assert time.perf_counter() - start < 2.0
    message = str(excinfo.value)
    assert repo_id in message and str(constants.HF_HUB_CACHE) in message and "\n" not in message
    assert f"hf download {repo_id}" in message  # the fix, spelled out


def test_missing_local_folder_is_not_mistaken_for_a_repo(module, tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint folder"):
        module.load_policy(str(tmp_path / "absent" / "tiny"))


# -- cameras -------------------------------------------------------------------------------------
def test_cameras_are_embedded_in_camera_keys_order(tiny):
    seen: list = []

    def record(image):  # remembers each camera's image mean: the two cameras differ
        seen.append(round(((image + 1) / 2).mean().item(), 5))
        tokens = tiny.info.native_grid[0] * tiny.info.native_grid[1]
        return torch.zeros(image.shape[0], tokens, tiny.info.lm_width)

    raw = make_raw(batch=1)
    raw[CAMERAS[0]] = torch.full_like(raw[CAMERAS[0]], 0.25)
    raw[CAMERAS[1]] = torch.full_like(raw[CAMERAS[1]], 0.75)
    with tiny.image_embedder(record):
        tiny.sample_actions(tiny.preprocess(raw), fixed_noise_time(tiny, 1)[0])
    assert seen[:2] == [0.25, 0.75]


# -- the real release's geometry -----------------------------------------------------------------
def test_real_shapes_agree_with_the_adapters_info(module):
    shapes = module.check_real_shapes()
    rows, cols = module.INFO_REAL.native_grid
    assert shapes["tokens_per_camera"] == rows * cols
    assert shapes["lm_width"] == module.INFO_REAL.lm_width
