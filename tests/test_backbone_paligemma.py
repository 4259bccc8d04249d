"""What pi0 and pi0.5 share beyond the adapter contract (backbones.paligemma, paligemma_load):
LeRobot's own loss, the native tower before PaliGemma's projector, the base releases' cameras."""

from __future__ import annotations

import pytest
import torch

from backbones import paligemma_load, pi0, pi05
from tests.backbone_data import (
    ACTION_DIM, CAMERAS, STATE_DIM, build_tiny, family_name, fixed_noise_time, make_raw, make_stats,
)

PALIGEMMA = (pi05, pi0)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module", params=PALIGEMMA, ids=lambda m: family_name(m.__name__))
def module(request):
    return request.param


@pytest.fixture(scope="module")
def tiny(module):
    return build_tiny(module)


def test_tiny_geometry(tiny):
    assert tiny.info.native_grid == (4, 4) and tiny.info.lm_width == 64
    assert tuple(tiny.policy.config.image_features) == CAMERAS


def test_loss_matches_lerobots_own_loss_without_padding(tiny, monkeypatch):
    # LeRobot's forward draws its own noise and time (and pads and passes the state itself for
    # pi0): equal only when ours feeds the same.
    batch = tiny.preprocess(make_raw())
    noise, flow_time = fixed_noise_time(tiny, 2)
    monkeypatch.setattr(tiny.policy.model, "sample_noise", lambda shape, device: noise)
    monkeypatch.setattr(tiny.policy.model, "sample_time", lambda size, device: flow_time)
    theirs, _ = tiny.policy.forward(batch, reduction="none")
    assert torch.allclose(tiny.loss(batch, noise, flow_time), theirs, rtol=1e-6, atol=1e-7)


def test_native_tower_grid_is_siglip_before_the_projector(tiny):
    image = torch.rand(2, 3, 64, 64) * 2 - 1
    grid = tiny.native_tower_grid(image)
    assert grid.shape == (2, 32, 4, 4)
    paligemma = tiny.policy.model.paligemma_with_expert.paligemma.model
    projected = paligemma.multi_modal_projector(grid.flatten(2).transpose(1, 2))
    embedded = tiny.policy.model.paligemma_with_expert.embed_image(image)
    assert torch.allclose(projected, embedded, atol=1e-6)


def test_libero_view_of_the_base_release_config(module):
    from lerobot.configs import FeatureType, PolicyFeature

    family = module.FAMILY
    base_cameras = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
    inputs = {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, 224, 224))
              for c in base_cameras}
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (32,))
    config = family.lerobot_class("configuration", "Config")(
        input_features=inputs, device="cpu",
        output_features={"action": PolicyFeature(FeatureType.ACTION, (32,))})
    rename_map, camera_keys = paligemma_load.adapt_real_config(config, make_stats(), family)
    assert camera_keys == CAMERAS
    assert [rename_map[k] for k in CAMERAS] == list(config.image_features)
    assert "observation.images.right_wrist_0_rgb" not in config.input_features
    assert config.output_features["action"].shape == (ACTION_DIM,)
    assert config.input_features["observation.state"].shape == (STATE_DIM,)


def test_dropping_an_unfed_camera_equals_lerobots_masked_empty_camera(module, tiny):
    # Why adapt_real_config may drop a base release's unmapped camera: LeRobot would feed it as
    # a masked -1 image, which neither attends nor shifts positions: same weights without that
    # camera give bit-identical actions and losses.
    cameras = (*CAMERAS, "observation.images.right_wrist")
    with_empty = build_tiny(module, cameras=cameras)
    raw = make_raw()
    noise, flow_time = fixed_noise_time(tiny, 2)
    batch, batch_empty = tiny.preprocess(raw), with_empty.preprocess(raw)
    assert torch.equal(tiny.sample_actions(batch, noise), with_empty.sample_actions(batch_empty, noise))
    assert torch.equal(tiny.loss(batch, noise, flow_time), with_empty.loss(batch_empty, noise, flow_time))


def test_real_release_geometry(module):
    # pi0_base and pi05_base: SigLIP So400m at 224 px / patch 14, gemma_2b (check_real_shapes
    # builds them and compares with INFO_REAL: tests/test_backbone_contract.py).
    assert (module.INFO_REAL.native_grid, module.INFO_REAL.lm_width) == ((16, 16), 2048)


def test_the_module_is_its_familys_adapter_member_by_member(module):
    # pi0.py and pi05.py unpack paligemma_adapter's fields by position: each name must hold
    # the member of that name.
    adapter = module._ADAPTER
    assert all(getattr(module, name) is getattr(adapter, name) for name in adapter._fields)
    assert module.BACKBONE_CLASS.family is module.FAMILY
    assert module.INFO_REAL.name == module.FAMILY.policy_type
    assert module.BACKBONE_CLASS.__name__ == f"{module.FAMILY.class_prefix}Backbone"
    assert module.MARKER_FILE == f"graftbench_{module.FAMILY.policy_type}.json"
