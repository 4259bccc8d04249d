"""pi0.5's own (backbones.pi05): the state as prompt text, QUANTILES normalisation, the pinned
tiny patches. The adapter contract: tests/test_backbone_contract.py; what pi0 shares:
tests/test_backbone_paligemma.py."""

from __future__ import annotations

import pytest
import torch

from backbones import pi05
from backbones.tiny_paligemma import TinyPaliGemmaArch, tiny_paligemma_patches, tiny_vocabulary
from tests.backbone_data import build_tiny, make_raw, make_stats


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def tiny():
    return build_tiny(pi05)


def test_state_is_prompt_text_and_every_token_is_known(tiny):
    batch = tiny.preprocess(make_raw())
    (step,) = [s for s in tiny.preprocessor.steps if type(s).__name__ == "TokenizerProcessorStep"]
    unk = step.input_tokenizer.convert_tokens_to_ids("<unk>")
    assert batch["task"][0].startswith("Task: pick up the red block") and "State: " in batch["task"][0]
    assert not (batch["observation.language.tokens"] == unk).any()
    assert all(str(b) in tiny_vocabulary() for b in range(256))
    moved = {**make_raw(), "observation.state": make_raw()["observation.state"] + 1.0}
    assert not torch.equal(tiny.preprocess(moved)["observation.language.tokens"],
                           batch["observation.language.tokens"])


def test_patches_are_scoped_and_pinned(monkeypatch):
    import lerobot
    from lerobot.policies.pi05 import modeling_pi05

    original = modeling_pi05.get_gemma_config
    with pytest.raises(KeyError):
        with tiny_paligemma_patches(TinyPaliGemmaArch()):
            assert modeling_pi05.get_gemma_config("gemma_2b").width == TinyPaliGemmaArch().vlm_width
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
