"""pi0's own (backbones.pi0): the state as ONE continuous token, MEAN_STD normalisation, LeRobot's
own sampler, checkpoints of another type refused. The adapter contract:
tests/test_backbone_contract.py; what pi0.5 shares: tests/test_backbone_paligemma.py."""

from __future__ import annotations

import json

import pytest
import torch

from backbones import pi0, pi05
from tests.backbone_data import (
    ACTION_DIM, STATE_DIM, build_tiny, fixed_noise_time, make_raw, make_stats,
)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny():
    return build_tiny(pi0)


def test_tiny_build_projects_the_padded_state(tiny):
    assert tiny.policy.model.state_proj.in_features == tiny.policy.config.max_state_dim == 32


def test_state_enters_as_a_token_not_as_prompt_text(tiny):
    raw = make_raw()
    other = {**raw, "observation.state": raw["observation.state"] + 1.0}
    batch, batch_other = tiny.preprocess(raw), tiny.preprocess(other)
    assert batch["task"][0] == "pick up the red block and place it on the plate\n"  # no "State:"
    assert torch.equal(batch["observation.language.tokens"], batch_other["observation.language.tokens"])
    noise, flow_time = fixed_noise_time(tiny, 2)
    assert not torch.allclose(tiny.loss(batch, noise, flow_time), tiny.loss(batch_other, noise, flow_time))
    assert not torch.allclose(tiny.sample_actions(batch, noise), tiny.sample_actions(batch_other, noise))


def test_sampler_matches_lerobots_own_sampler(tiny):
    batch = tiny.preprocess(make_raw())
    noise, _ = fixed_noise_time(tiny, 2)
    images, img_masks = tiny.policy._preprocess_images(batch)
    theirs = tiny.policy.model.sample_actions(
        images, img_masks, batch["observation.language.tokens"],
        batch["observation.language.attention_mask"], tiny.policy.prepare_state(batch), noise=noise,
    )[:, :, :ACTION_DIM]
    assert torch.equal(tiny.sample_actions(batch, noise), theirs)


def test_state_normalisation_is_mean_std(tiny):
    stats = make_stats()
    state_mean, state_std = (torch.tensor(stats["observation.state"][k], dtype=torch.float32)
                             for k in ("mean", "std"))
    raw_batch = make_raw()
    raw_batch["observation.state"] = (state_mean + state_std).expand(2, STATE_DIM).clone()
    normalised_state = tiny.preprocess(raw_batch)["observation.state"]
    assert torch.allclose(normalised_state, torch.ones(2, STATE_DIM), atol=1e-5)


def test_stats_need_mean_and_std_not_quantiles():
    without_quantiles = make_stats()
    for key in ("observation.state", "action"):
        del without_quantiles[key]["q01"], without_quantiles[key]["q99"]
    pi0.build_tiny_policy(without_quantiles)  # pi0 does not read them
    without_std = make_stats()
    del without_std["observation.state"]["std"]
    with pytest.raises(ValueError, match=r"'std'.*MEAN_STD"):
        pi0.build_tiny_policy(without_std)


def test_a_checkpoint_of_another_type_or_on_relative_actions_is_refused(tiny, tmp_path):
    pi05.save_pretrained(build_tiny(pi05), tmp_path / "a_pi05")
    with pytest.raises(ValueError, match="'pi05' checkpoint, not 'pi0'"):
        pi0.load_policy(str(tmp_path / "a_pi05"))

    pi0.save_pretrained(tiny, tmp_path / "relative")
    assert (tmp_path / "relative" / pi0.MARKER_FILE).is_file()
    config = tmp_path / "relative" / "config.json"
    config.write_text(json.dumps({**json.loads(config.read_text()), "use_relative_actions": True}))
    with pytest.raises(ValueError, match="use_relative_actions"):
        pi0.load_policy(str(tmp_path / "relative"))
