"""Processors of grafted policies: the base policy's own steps, with the tokenizer carried inside
the checkpoint (`graft_tokenizer_processor`) so a copied folder needs no path of the machine
that wrote it and no hub download of the tokenizer.

LeRobot finds `make_<type>_pre_post_processors` here by convention when it builds processors
from a config alone; a saved checkpoint's processors load from its JSON and this module's step.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from lerobot.processor import ProcessorStepRegistry
from lerobot.processor.tokenizer_processor import TokenizerProcessorStep

from lerobot_policy_graft.families import PI0, PI05, SMOLVLA, GraftFamily

TOKENIZER_STATE_KEY = "tokenizer_files"


def _files_to_tensor(files: dict[str, str]) -> torch.Tensor:
    """{file name: text} -> (N,) uint8: the JSON bytes, storable in a safetensors file."""
    blob = json.dumps(files, sort_keys=True).encode()
    return torch.frombuffer(bytearray(blob), dtype=torch.uint8).clone()


def _tensor_to_folder(blob: torch.Tensor) -> Path:
    """The tokenizer files unpacked into a content-addressed folder under the temp dir."""
    data = bytes(blob.to(torch.uint8).cpu().numpy().tobytes())
    digest = hashlib.sha256(data).hexdigest()[:16]
    folder = Path(tempfile.gettempdir()) / "graft_tokenizers" / digest
    if not (folder / ".complete").is_file():
        folder.mkdir(parents=True, exist_ok=True)
        for name, text in json.loads(data).items():
            tmp = folder / f".{name}.{os.getpid()}"
            tmp.write_text(text)
            tmp.replace(folder / name)
        (folder / ".complete").write_text("")
    return folder


@ProcessorStepRegistry.register(name="graft_tokenizer_processor")
@dataclass
class GraftTokenizerProcessorStep(TokenizerProcessorStep):
    """LeRobot's TokenizerProcessorStep whose tokenizer files travel in its state file
    (policy_preprocessor_step_<i>_graft_tokenizer_processor.safetensors), not as a path or id."""

    bundled: bool = True

    def __post_init__(self) -> None:
        if self.tokenizer is None and self.tokenizer_name is None and self.bundled:
            self.input_tokenizer = None  # arrives with load_state_dict
            return
        super().__post_init__()

    @classmethod
    def from_step(cls, step: TokenizerProcessorStep) -> "GraftTokenizerProcessorStep":
        """The same step (same tokenizer object and settings), bundling its tokenizer."""
        return cls(tokenizer=step.input_tokenizer, max_length=step.max_length,
                   task_key=step.task_key, padding_side=step.padding_side,
                   padding=step.padding, truncation=step.truncation)

    def get_config(self) -> dict[str, Any]:
        config = super().get_config()
        config.pop("tokenizer_name", None)
        return {**config, "bundled": True}

    def state_dict(self) -> dict[str, torch.Tensor]:
        if self.input_tokenizer is None:
            raise RuntimeError("graft_tokenizer_processor has no tokenizer to save")
        with tempfile.TemporaryDirectory() as tmp:
            self.input_tokenizer.save_pretrained(tmp)
            files = {p.name: p.read_text() for p in sorted(Path(tmp).iterdir()) if p.is_file()}
        return {TOKENIZER_STATE_KEY: _files_to_tensor(files)}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        from transformers import AutoTokenizer

        if TOKENIZER_STATE_KEY not in state:
            raise KeyError(f"graft_tokenizer_processor state lacks {TOKENIZER_STATE_KEY!r}; "
                           f"has {sorted(state)}: re-export the checkpoint")
        self.input_tokenizer = AutoTokenizer.from_pretrained(
            str(_tensor_to_folder(state[TOKENIZER_STATE_KEY])))


def bundle_tokenizer(pipeline) -> None:
    """Swap the pipeline's TokenizerProcessorStep for the bundling one, in place."""
    for i, step in enumerate(pipeline.steps):
        if type(step) is TokenizerProcessorStep:
            pipeline.steps[i] = GraftTokenizerProcessorStep.from_step(step)


def bundled_processors(family: GraftFamily):
    """`make_graft_<type>_pre_post_processors` of `family`: its LeRobot processors (built from
    the config), tokenizer bundled."""
    def make(config, dataset_stats=None):
        module = importlib.import_module(
            f"lerobot.policies.{family.policy_type}.processor_{family.policy_type}")
        make_base = getattr(module, f"make_{family.policy_type}_pre_post_processors")
        pipelines = make_base(config, dataset_stats=dataset_stats)
        bundle_tokenizer(pipelines[0])
        return pipelines

    make.__name__ = make.__qualname__ = f"make_graft_{family.policy_type}_pre_post_processors"
    return make


# LeRobot looks these up by name (factory._make_processors_from_policy_config).
make_graft_smolvla_pre_post_processors = bundled_processors(SMOLVLA)
make_graft_pi05_pre_post_processors = bundled_processors(PI05)
make_graft_pi0_pre_post_processors = bundled_processors(PI0)
