"""Device placement, checked without a GPU: the policy on the META device.

Every tensor that reaches a policy must be on the policy's device; on CUDA a CPU tensor mixed in
crashes the first real run. On the CPU everything is on the CPU, so nothing can show it. With the
policy (weights and processor device step) on "meta", torch raises "Tensor on device cpu is not
on the expected device meta" at the first op that mixes a harness CPU tensor in, exactly where
CUDA would. Where LeRobot's own code needs data-dependent values (SmolVLA's sampler calls
`.item()`), the tensors are checked at the policy's entry instead.
"""

from __future__ import annotations

import contextlib

import pytest
import torch

from backbones import pi0, pi05, smolvla
from tests.backbone_data import CAMERAS, make_raw, make_stats

CHUNK = 10


class _Entered(Exception):
    pass


def on_meta(backbone):
    """Move the policy and its pre-processor's device step to the meta device (in place)."""
    backbone.policy.to("meta")
    backbone.policy.config.device = "meta"
    for step in backbone.preprocessor.steps:
        if type(step).__name__ == "DeviceProcessorStep":
            step.device, step.tensor_device = "meta", torch.device("meta")
    return backbone


def tensors_off(value, device: str) -> list[str]:
    """Paths of the tensors in a (nested) batch that are not on `device`."""
    if torch.is_tensor(value):
        return [] if value.device.type == device else [str(value.device)]
    if isinstance(value, dict):
        return [f"{k}: {d}" for k, v in value.items() for d in tensors_off(v, device)]
    return []


@contextlib.contextmanager
def entry_checked(policy, method: str):
    """Within the block, `policy.method(batch, **kwargs)` checks every tensor argument is on the
    meta device, then stops (raises _Entered) before LeRobot's data-dependent code runs."""
    def check(batch, *args, **kwargs):
        off = tensors_off(batch, "meta") + tensors_off(dict(kwargs), "meta")
        off += [str(a.device) for a in args if torch.is_tensor(a) and a.device.type != "meta"]
        assert not off, f"{method} received tensors off the policy's device: {off}"
        raise _Entered

    setattr(policy, method, check)
    try:
        yield
    finally:
        delattr(policy, method)


@pytest.fixture(params=["smolvla", "pi05", "pi0"])
def meta_backbone(request):
    # SmolVLM's patch embedding indexes by its all-True patch mask (nonzero): on meta, assume it.
    import torch.fx.experimental._config as fx_config

    with fx_config.patch(meta_nonzero_assume_all_nonzero=True):
        yield _meta_backbone(request.param)


def _meta_backbone(name: str):
    module = {"smolvla": smolvla, "pi05": pi05, "pi0": pi0}[name]
    backbone = module.build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK, seed=0)
    backbone.freeze()
    return on_meta(backbone), make_raw()


def harness_noise_time(backbone, batch_size: int = 2):
    """Noise and time as the harness draws them: on the CPU, from a CPU generator."""
    gen = torch.Generator().manual_seed(0)
    noise = torch.randn((batch_size, CHUNK, backbone.info.max_action_dim), generator=gen)
    return noise, backbone.sample_time(batch_size, gen)


def test_prepared_batch_is_on_the_policy_device(meta_backbone):
    backbone, raw = meta_backbone
    assert tensors_off(backbone.preprocess(raw), "meta") == []


def test_loss_reaches_the_model_with_every_tensor_on_its_device(meta_backbone):
    # Both adapters end in the policy's inner model forward (images, masks, tokens, state or
    # actions, noise, time): the harness's CPU noise and time must have been moved by then.
    backbone, raw = meta_backbone
    noise, flow_time = harness_noise_time(backbone)
    batch = backbone.preprocess(raw)
    with entry_checked(backbone.policy.model, "forward"), pytest.raises(_Entered):
        backbone.loss(batch, noise, flow_time)


def test_sampler_gets_every_tensor_on_the_policy_device(meta_backbone):
    backbone, raw = meta_backbone
    noise, _ = harness_noise_time(backbone)
    batch = backbone.preprocess(raw)
    with entry_checked(backbone.policy, "predict_action_chunk"), pytest.raises(_Entered):
        backbone.sample_actions(batch, noise)


def test_graft_feed_returns_tokens_on_the_device_of_the_image(meta_backbone):
    # Cached features live on the CPU; the tokens must come out where the policy's images are.
    from graftcore.graft import GraftFeed, Projector

    backbone, _ = meta_backbone
    projector = Projector(16, backbone.info.lm_width).to("meta")
    feed = GraftFeed(projector, backbone.camera_keys, backbone.info.native_grid)
    tokens = backbone.info.native_grid[0] * backbone.info.native_grid[1]
    feed.bind({k: torch.randn(2, tokens, 16) for k in backbone.camera_keys})
    out = [feed(torch.empty(2, 3, 64, 64, device="meta")) for _ in backbone.camera_keys]
    assert all(t.device.type == "meta" for t in out)


@pytest.mark.parametrize("name", ["pi05", "pi0"])
def test_paligemma_grafted_loss_and_sampler_run_whole_on_meta(name):
    # pi0.5's and pi0's forward and sampler need no data-dependent value: run them whole on meta
    # (pi0's state token included).
    from graftcore.graft import GraftFeed, Projector

    backbone, raw = _meta_backbone(name)
    projector = Projector(16, backbone.info.lm_width).to("meta")
    feed = GraftFeed(projector, backbone.camera_keys, backbone.info.native_grid)
    tokens = backbone.info.native_grid[0] * backbone.info.native_grid[1]
    noise, flow_time = harness_noise_time(backbone)
    batch = backbone.preprocess(raw)
    with backbone.image_embedder(feed):
        feed.bind({k: torch.randn(2, tokens, 16) for k in backbone.camera_keys})
        loss = backbone.loss(batch, noise, flow_time)
        feed.bind({k: torch.randn(2, tokens, 16) for k in backbone.camera_keys})
        actions = backbone.sample_actions(batch, noise)
    assert loss.device.type == actions.device.type == "meta"
