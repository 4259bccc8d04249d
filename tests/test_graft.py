import pytest
import torch

from bench.cell.freeze import assert_only_trainable, trainable_parameters
from graftcore.graft import GraftFeed, Projector


def test_projector_is_one_linear_behind_a_parameter_free_layernorm():
    proj = Projector(384, 960)
    assert trainable_parameters(proj) == 384 * 960 + 960  # the paper's ~0.4M DINOv2-S -> SmolVLA
    assert list(proj.norm.parameters()) == []
    out = proj(torch.randn(2, 64, 384) * 5 + 3)
    assert out.shape == (2, 64, 960)


def test_layernorm_makes_the_projector_blind_to_feature_scale():
    proj = Projector(16, 8)
    x = torch.randn(3, 4, 16)
    torch.testing.assert_close(proj(x), proj(x * 7.0 + 2.0), atol=1e-5, rtol=1e-5)


def test_freeze_check_counts_and_fails_loudly():
    proj, frozen = Projector(4, 3), torch.nn.Linear(5, 5)
    with pytest.raises(AssertionError, match="freeze violated: 45 trainable.*expected 15"):
        assert_only_trainable(15, proj, frozen)
    frozen.requires_grad_(False)
    assert_only_trainable(15, proj, frozen)


def test_feed_serves_cameras_in_order_and_checks_consumption():
    proj = Projector(2, 3)
    feed = GraftFeed(proj, ("a", "b"), (1, 1))
    fa, fb = torch.zeros(2, 1, 2), torch.ones(2, 1, 2) * torch.tensor([1.0, -1.0])
    feed.bind({"a": fa, "b": fb})
    img = torch.zeros(2, 3, 8, 8)
    torch.testing.assert_close(feed(img), proj(fa))
    with pytest.raises(RuntimeError, match="consumed only 1 of 2"):
        feed.assert_consumed()
    torch.testing.assert_close(feed(img), proj(fb))
    feed.assert_consumed()
    with pytest.raises(RuntimeError, match="more camera embeddings"):
        feed(img)
    with pytest.raises(KeyError, match="missing cameras"):
        feed.bind({"a": fa})


def test_feed_from_a_tower_pools_to_the_grid():
    proj = Projector(3, 2)
    feed = GraftFeed(proj, ("a",), (2, 2), tower=lambda im: im)  # the image itself as a grid
    img = torch.arange(2 * 3 * 4 * 4, dtype=torch.float32).reshape(2, 3, 4, 4)
    pooled = torch.nn.functional.adaptive_avg_pool2d(img, (2, 2)).flatten(2).transpose(1, 2)
    torch.testing.assert_close(feed(img), proj(pooled))
