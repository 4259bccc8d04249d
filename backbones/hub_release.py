"""The base releases at tiny size, shaped as the hub's: each adapter module's
`write_hub_release` (backbones.seam.AdapterModule) writes its release here into a Hugging Face
cache; bench/offline_hub.py builds the whole offline world (docstring there: what is real, what tiny).

Takes the adapter module as an argument (it imports no adapter), so the adapters may import it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ondisk.hubcache import snapshot_dir

# Commits of repos graftbench does not pin (the cache's main points at them).
VLM_FAKE_SHA = "7b375e1b73b11138ff12fe22c8f2822d8fe03467"  # smolvla's VLM_REPO_ID
TOKENIZER_FAKE_SHA = "35e4f46485b4d07967e7e9935bc3786aad50687c"  # PALIGEMMA_TOKENIZER_REPO
SMOLVLA_BASE_CAMERAS = tuple(f"observation.images.camera{i}" for i in (1, 2, 3))
PALIGEMMA_BASE_CAMERAS = tuple(f"observation.images.{c}"  # pi05_base and pi0_base
                               for c in ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"))


def fake_stats(dim: int, scale: float) -> dict:
    """Stats of one `dim`-wide feature, every kind LeRobot normalises with (mean/std, min/max,
    quantiles), spread growing with the index."""
    spread = np.linspace(0.5, 2.0, dim) * scale
    return {"mean": np.zeros(dim), "std": spread / 2, "min": -spread * 1.5, "max": spread * 1.5,
            "q01": -spread, "q99": spread}


def release_stats(cameras, dim: int) -> dict:
    """Dataset stats of a release: `dim`-wide state and action, mean/std of each camera."""
    stats = {"observation.state": fake_stats(dim, 1.0), "action": fake_stats(dim, 0.5)}
    for cam in cameras:
        stats[cam] = {"mean": np.full((3, 1, 1), 0.5), "std": np.full((3, 1, 1), 0.25)}
    return stats


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data, indent=2))


def _edit_steps(path: Path, configs: dict[str, dict], drop_state_files: bool = False) -> None:
    """Rewrite a saved processor JSON as the hub's is: `configs` {registry name: config keys to
    set} merged into those steps; `drop_state_files` removes every step's stats file entry."""
    def edit(data):
        for step in data["steps"]:
            step["config"].update(configs.get(step["registry_name"], {}))
            if drop_state_files:
                step.pop("state_file", None)
    _edit_json(path, edit)


def _so100_keyed_stats(snap: Path) -> None:
    """smolvla_base's saved stats: action stats under SO-100 dataset keys only, no state stats
    (docs/HUB_FACTS.md), so LeRobot's look-up by `action` / `observation.state` misses."""
    from safetensors.torch import load_file, save_file

    for path in snap.glob("policy_*processor_step_*_normalizer_processor.safetensors"):
        stats = load_file(str(path))
        save_file({f"so100.buffer.{k}": v for k, v in stats.items() if k.startswith("action.")},
                  str(path))


def write_smolvla_release(smolvla, hub_cache: Path, repo_id: str, revision: str | None) -> None:
    """lerobot/smolvla_base shaped (`smolvla`: the adapter module): SO-100 cameras and dims, VLM
    by its hub id, hub quirks."""
    snap = snapshot_dir(hub_cache, repo_id, revision)
    tiny = smolvla.build_tiny_policy(release_stats(SMOLVLA_BASE_CAMERAS, 6), SMOLVLA_BASE_CAMERAS,
                                     state_dim=6, action_dim=6, chunk_size=10, seed=0)
    smolvla.save_pretrained(tiny, snap)
    vlm = snapshot_dir(hub_cache, smolvla.VLM_REPO_ID, VLM_FAKE_SHA)
    shutil.copytree(snap / smolvla.VENDORED_VLM_DIR, vlm, dirs_exist_ok=True)
    shutil.rmtree(snap / smolvla.VENDORED_VLM_DIR)

    def config(data):
        data.update(vlm_model_name=smolvla.VLM_REPO_ID, load_vlm_weights=True)
    _edit_json(snap / "config.json", config)

    # The hub files: saved on CUDA, tokenizer by the VLM's hub id, stats under SO-100 keys only.
    _edit_steps(snap / "policy_preprocessor.json",
                {"device_processor": {"device": "cuda"},
                 "tokenizer_processor": {"tokenizer_name": smolvla.VLM_REPO_ID}})
    _so100_keyed_stats(snap)


def write_paligemma_release(module, hub_cache: Path, repo_id: str, revision: str | None,
                            device: str) -> None:
    """The base release of a PaliGemma family (`module`: pi05, pi0) shaped as the hub's:
    DROID-style cameras, 32 dims, `features: {}`, no stats file, its saved `device`, tokenizer by
    hub id."""
    from backbones.paligemma import PALIGEMMA_TOKENIZER_REPO, TOKENIZER_SUBDIR

    snap = snapshot_dir(hub_cache, repo_id, revision)
    cameras = PALIGEMMA_BASE_CAMERAS
    tiny = module.build_tiny_policy(release_stats(cameras, 32), cameras, state_dim=32,
                                    action_dim=32, chunk_size=10, seed=0)
    module.save_pretrained(tiny, snap)
    # shared by both families
    tokenizer = snapshot_dir(hub_cache, PALIGEMMA_TOKENIZER_REPO, TOKENIZER_FAKE_SHA)
    shutil.copytree(snap / TOKENIZER_SUBDIR, tokenizer, dirs_exist_ok=True)
    shutil.rmtree(snap / TOKENIZER_SUBDIR)
    (tokenizer / "config.json").write_text(json.dumps(  # AutoTokenizer reads it first
        {"architectures": ["PaliGemmaForConditionalGeneration"], "model_type": "paligemma"}))
    marker = json.loads((snap / module.MARKER_FILE).read_text())
    (snap / module.MARKER_FILE).write_text(json.dumps({"tiny_arch": marker["tiny_arch"]}, indent=2))
    for stats_file in snap.glob("policy_*processor_step_*.safetensors"):
        stats_file.unlink()

    hub_steps = {"normalizer_processor": {"features": {}}, "unnormalizer_processor": {"features": {}},
                 "device_processor": {"device": device},
                 "tokenizer_processor": {"tokenizer_name": PALIGEMMA_TOKENIZER_REPO}}
    _edit_steps(snap / "policy_preprocessor.json", hub_steps, drop_state_files=True)
    _edit_steps(snap / "policy_postprocessor.json", {**hub_steps, "device_processor": {"device": "cpu"}},
                drop_state_files=True)
