"""The exported plugin stands alone: a tiny graft of each family, exported by graftbench, then in a
fresh interpreter where graftbench's packages (bench, encoders, backbones, ondisk) cannot be
imported: loaded through LeRobot's own factory (strict keys), scored on the held-out windows of
its record to the record's MSE, and trained one optimizer step, as on a machine that has LeRobot
and the plugin only."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from bench.export import export_cell
from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY, with_overrides
from bench.results.parts import NORMALIZED, RAW
from bench.results.store import ResultStore
from bench.loops.evaluate import window_noise
from bench.cell.service import run_cell
from bench.suites.windows import raw_batch
from tests.worlds import lent_workspace

pytest.importorskip("lerobot_policy_graft", reason="install the plugin: scripts/install.sh")

FAMILIES = ("smolvla", "pi05", "pi0")
HARNESS = ("bench", "encoders", "backbones", "ondisk")  # graftbench's packages
PROFILE = with_overrides(TINY, steps=2)
ENCODER = "dinov2_s"
CLASSES = {"smolvla": "GraftSmolVLAPolicy", "pi05": "GraftPI05Policy", "pi0": "GraftPI0Policy"}

# Run as `python -I -c STANDALONE JOB.json`: no current folder, PYTHONPATH or user site on the
# path, and graftbench's packages refused even where its editable install puts them on it.
STANDALONE = r'''
import importlib.abc, json, sys

JOB = json.loads(open(sys.argv[1]).read())


class NoGraftbench(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in JOB["harness"]:
            raise ModuleNotFoundError(f"{name}: graftbench is not installed here", name=name)


sys.meta_path.insert(0, NoGraftbench())

import torch
from lerobot.configs import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
from lerobot.policies.factory import make_policy, make_pre_post_processors
from lerobot.processor import TransitionKey, create_transition
from lerobot.utils.import_utils import register_third_party_plugins
from safetensors.torch import load_model

register_third_party_plugins()  # what lerobot-train and lerobot-eval do first


def step_of(pipeline, name):
    (step,) = [s for s in pipeline.steps if type(s).__name__ == name]
    return lambda actions: step(create_transition(action=actions))[TransitionKey.ACTION]


def load(export):
    """lerobot-train's way: the config from the folder, the policy by LeRobot's factory."""
    config = PreTrainedConfig.from_pretrained(export["folder"])
    config.pretrained_path = export["folder"]
    meta = LeRobotDatasetMetadata(export["repo_id"], root=export["root"])
    policy = make_policy(config, ds_meta=meta)
    pre, post = make_pre_post_processors(config, pretrained_path=export["folder"])
    missing, unexpected = load_model(policy, f"{export['folder']}/model.safetensors", strict=False)
    return policy, pre, post, {"missing": sorted(missing), "unexpected": sorted(unexpected)}


@torch.no_grad()
def heldout_mse(policy, pre, post, batches, spaces):
    """Offline action MSE as graftbench scores it: sampled chunks with the window's noise vs.
    ground truth, real action dims and real chunk steps only, mean over windows."""
    normalize, unnormalize = step_of(pre, "NormalizerProcessorStep"), step_of(post, "UnnormalizerProcessorStep")
    policy.eval()
    per_window = {space: [] for space in spaces}
    for raw, noise in batches:
        pred = policy.predict_action_chunk(dict(pre(dict(raw))), noise=noise)
        policy.reset()
        target, valid = raw["action"], ~raw["action_is_pad"]
        pred = pred[..., : target.shape[-1]].float().cpu()
        pairs = {spaces[0]: (pred, normalize(target).float().cpu()),
                 spaces[1]: (unnormalize(pred).float().cpu(), target)}
        for space, (p, t) in pairs.items():
            sq = (p - t).pow(2).mean(dim=-1) * valid
            per_window[space].append(sq.sum(dim=1) / valid.sum(dim=1).clamp(min=1))
    return {space: float(torch.cat(v).mean()) for space, v in per_window.items()}


def train_one_step(policy, pre, raw):
    """One step of LeRobot's own training: its optimizer preset over get_optim_params."""
    policy.train()
    params = dict(policy.named_parameters())
    trainable = sorted(n for n, p in params.items() if p.requires_grad)
    before = {n: p.detach().clone() for n, p in params.items() if n.startswith("graft.")}
    optimizer = policy.config.get_optimizer_preset().build(policy.get_optim_params())
    loss, _ = policy.forward(pre(dict(raw)))
    loss.backward()
    optimizer.step()
    changed = sorted(n for n, value in before.items() if not torch.equal(value, params[n]))
    return {"loss": float(loss), "trainable": trainable, "changed": changed}


out = {}
for family, export in JOB["exports"].items():
    policy, pre, post, keys = load(export)
    batches = torch.load(export["batches"], weights_only=True)
    out[family] = {"type": policy.config.type, "class": type(policy).__name__, **keys,
                   "mse": heldout_mse(policy, pre, post, batches, JOB["spaces"]),
                   **train_one_step(policy, pre, batches[0][0])}
out["harness_modules"] = sorted(m for m in sys.modules if m.split(".")[0] in JOB["harness"])
open(JOB["out"], "w").write(json.dumps(out))
'''


def heldout_batches(ws, family: str) -> list:
    """(raw batch, noise) per evaluation batch of the cell's held-out windows, as graftbench's
    scorer (bench.loops.evaluate.score) builds them."""
    p, suite = ws.profile.protocol, ws.suite("spatial")
    info = ws.backbone(family, "spatial").info
    windows = ws.split("spatial").windows
    return [(raw_batch(suite, frames, info.chunk_size, with_images=True),
             window_noise(frames, info.chunk_size, info.max_action_dim, p.eval_noise_seed))
            for frames in windows.split(p.eval_batch_size)]


@pytest.fixture(scope="module")
def standalone(tmp_path_factory, one_torch_thread):
    """One float32-feature graft cell per family, exported; then ONE fresh interpreter (its
    imports cost most) loads, scores and trains each export. -> (records, its findings)."""
    root = tmp_path_factory.mktemp("standalone")
    ws = lent_workspace(PROFILE, ResultStore(root / "results"), feature_dtype="float32")
    records, exports = {}, {}
    for family in FAMILIES:
        records[family] = run_cell(CellSpec("graft", family, "spatial", 0, ENCODER), ws)
        folder = export_cell(root / "results", records[family].cell_id, root / family,
                             lend_from=ws)
        torch.save(heldout_batches(ws, family), root / f"{family}-batches.pt")
        suite = ws.suite("spatial")
        exports[family] = {"folder": str(folder), "batches": str(root / f"{family}-batches.pt"),
                           "repo_id": suite.repo_id, "root": str(suite.root)}
    job = {"exports": exports, "harness": HARNESS, "spaces": [NORMALIZED, RAW],
           "out": str(root / "findings.json")}
    (root / "job.json").write_text(json.dumps(job))
    done = subprocess.run([sys.executable, "-I", "-c", STANDALONE, str(root / "job.json")],
                          cwd=root, capture_output=True, text=True, timeout=600,
                          env={"PATH": "/usr/bin:/bin", "HF_HUB_OFFLINE": "1",
                               "OMP_NUM_THREADS": "1", "HOME": str(root)})
    assert done.returncode == 0, done.stderr[-4000:]
    return records, json.loads((root / "findings.json").read_text())


@pytest.mark.slow
def test_graftbench_is_never_imported(standalone):
    _, found = standalone
    assert found["harness_modules"] == []


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_lerobots_factory_loads_the_export_strictly(standalone, family):
    _, found = standalone
    assert found[family]["type"] == f"graft_{family}"
    assert found[family]["class"] == CLASSES[family]
    assert (found[family]["missing"], found[family]["unexpected"]) == ([], [])


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_the_export_scores_its_records_mse(standalone, family):
    records, found = standalone
    mse = found[family]["mse"]
    for space, value in records[family].scores.mse.items():
        assert mse[space] == value, (space, mse[space], value)  # the same code on the same CPU


@pytest.mark.slow
@pytest.mark.parametrize("family", FAMILIES)
def test_the_export_trains_its_projector_one_step(standalone, family):
    _, found = standalone
    projector = ["graft.projector.linear.bias", "graft.projector.linear.weight"]
    assert found[family]["trainable"] == projector
    assert found[family]["changed"] == projector  # the encoder stays frozen
    assert torch.isfinite(torch.tensor(found[family]["loss"]))
