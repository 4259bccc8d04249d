"""The real world's shape at tiny sizes: a Hugging Face cache in huggingface_hub's layout under
the REAL repo ids, so `--profile paper` runs offline through the same from_pretrained /
LeRobotDataset / timm loading code as on a GPU box with the real cache.

    .venv/bin/python -m bench.hubworld DIR    # then HF_HOME=DIR HF_HUB_OFFLINE=1 pytest bench --profile paper

What is real: repo ids, revisions (the pinned ones), the cache layout (`models--ORG--NAME/refs`,
`snapshots/<rev>/`), file names, config fields, camera names and widths of the releases
(smolvla_base: camera1/2/3, 6-dim SO-100 state/action; pi05_base and pi0_base: base_0_rgb /
left_wrist_0_rgb / right_wrist_0_rgb, 32-dim), the hub processor-JSON quirks (pi05_base and
pi0_base: normaliser `features: {}`, no stats file; device cpu for pi05_base, cuda for pi0_base;
smolvla_base: device cuda, stats under SO-100 keys only), LIBERO's
v3.0 dataset layout and feature names. What is tiny, and the only construction patches it forces
(nothing else is bypassed):
1. SmolVLM2: its config.json is a tiny SmolVLM (no patch: SmolVLA reads the VLM's config).
2. pi0.5 and pi0: `graftbench_pi05.json` / `graftbench_pi0.json` in the snapshot names the tiny
   arch; the adapter then builds under backbones.tiny_pi05's three model patches (Gemma variants,
   PaliGemma sizes, expert vocab). The tokenizer is read from google/paligemma-3b-pt-224 in the
   cache, unpatched.
3. timm: each weight repo's config.json carries `model_args` (the tiny architecture) and its
   pretrained_cfg input size; encoders.timm_encoders passes them to create_model(pretrained=True).
4. Data: the generated LIBERO-format suites (64 px images, 16 episodes per task) under the
   LIBERO repo ids.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

from backbones import get_entry
from backbones.paligemma import PALIGEMMA_TOKENIZER_REPO, TOKENIZER_SUBDIR
from backbones.smolvla import VENDORED_VLM_DIR, VLM_REPO_ID

FAKE_SHA = {  # commits for repos graftbench does not pin (the cache's main points at them)
    VLM_REPO_ID: "7b375e1b73b11138ff12fe22c8f2822d8fe03467",
    PALIGEMMA_TOKENIZER_REPO: "35e4f46485b4d07967e7e9935bc3786aad50687c",
}
DEFAULT_SHA = "0" * 40
SMOLVLA_BASE_CAMERAS = tuple(f"observation.images.camera{i}" for i in (1, 2, 3))
PALIGEMMA_BASE_CAMERAS = tuple(f"observation.images.{c}"  # pi05_base and pi0_base
                               for c in ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"))
PAPER_SUITES = ("spatial", "object")


def snapshot_dir(hub_cache: Path, repo_id: str, revision: str | None,
                 repo_type: str = "model") -> Path:
    """hub_cache/<type>s--ORG--NAME/snapshots/<rev>/ with refs/main -> rev (created)."""
    sha = revision or FAKE_SHA.get(repo_id, DEFAULT_SHA)
    folder = hub_cache / f"{repo_type}s--{repo_id.replace('/', '--')}"
    (folder / "refs").mkdir(parents=True, exist_ok=True)
    (folder / "refs" / "main").write_text(sha)
    snap = folder / "snapshots" / sha
    snap.mkdir(parents=True, exist_ok=True)
    return snap


def _stats(dim: int, scale: float) -> dict:
    spread = np.linspace(0.5, 2.0, dim) * scale
    return {"mean": np.zeros(dim), "std": spread / 2, "min": -spread * 1.5, "max": spread * 1.5,
            "q01": -spread, "q99": spread}


def _release_stats(cameras, dim: int) -> dict:
    stats = {"observation.state": _stats(dim, 1.0), "action": _stats(dim, 0.5)}
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


def write_smolvla_base(hub_cache: Path) -> None:
    """lerobot/smolvla_base shaped: SO-100 cameras and dims, VLM by its hub id, hub quirks."""
    from backbones import smolvla

    entry = get_entry("smolvla")
    snap = snapshot_dir(hub_cache, entry.repo_id, entry.revision)
    tiny = smolvla.build_tiny_policy(_release_stats(SMOLVLA_BASE_CAMERAS, 6), SMOLVLA_BASE_CAMERAS,
                                     state_dim=6, action_dim=6, chunk_size=10, seed=0)
    smolvla.save_pretrained(tiny, snap)
    vlm = snapshot_dir(hub_cache, VLM_REPO_ID, None)
    shutil.copytree(snap / VENDORED_VLM_DIR, vlm, dirs_exist_ok=True)
    shutil.rmtree(snap / VENDORED_VLM_DIR)

    def config(data):
        data.update(vlm_model_name=VLM_REPO_ID, load_vlm_weights=True)
    _edit_json(snap / "config.json", config)

    # The hub files: saved on CUDA, tokenizer by the VLM's hub id, stats under SO-100 keys only.
    _edit_steps(snap / "policy_preprocessor.json", {"device_processor": {"device": "cuda"},
                                                    "tokenizer_processor": {"tokenizer_name": VLM_REPO_ID}})
    _so100_keyed_stats(snap)


def write_paligemma_base(hub_cache: Path, name: str, device: str) -> None:
    """The base release of PaliGemma backbone `name` (pi05, pi0) shaped as the hub's: DROID-style
    cameras, 32 dims, `features: {}`, no stats file, its saved `device`, tokenizer by hub id."""
    from backbones import adapter_module

    module = adapter_module(name)
    entry = get_entry(name)
    snap = snapshot_dir(hub_cache, entry.repo_id, entry.revision)
    cameras = PALIGEMMA_BASE_CAMERAS
    tiny = module.build_tiny_policy(_release_stats(cameras, 32), cameras, state_dim=32,
                                    action_dim=32, chunk_size=10, seed=0)
    module.save_pretrained(tiny, snap)
    tokenizer = snapshot_dir(hub_cache, PALIGEMMA_TOKENIZER_REPO, None)  # shared by both families
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


def write_pi05_base(hub_cache: Path) -> None:
    """lerobot/pi05_base shaped: its processors saved with device cpu (docs/HUB_FACTS.md)."""
    write_paligemma_base(hub_cache, "pi05", device="cpu")


def write_pi0_base(hub_cache: Path) -> None:
    """lerobot/pi0_base shaped: its pre-processor saved with device cuda (docs/HUB_FACTS.md)."""
    write_paligemma_base(hub_cache, "pi0", device="cuda")


def write_timm_weights(hub_cache: Path, names=("siglip", "dinov2_s", "fastvit", "repvit")) -> None:
    """timm/<model>.<tag>: tiny-architecture weights plus a config.json naming that architecture."""
    from safetensors.torch import save_file

    from encoders import get_spec
    from encoders.timm_encoders import TINY_SEED, hub_weights

    import timm

    for name in names:
        spec = get_spec(name)
        repo_id, revision, _ = hub_weights(spec.timm_name)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(TINY_SEED + 1)  # not the tiny profile's init: "pretrained" weights
            model = timm.create_model(spec.timm_name, pretrained=False, num_classes=0,
                                      **spec.tiny_kwargs)
        snap = snapshot_dir(hub_cache, repo_id, revision)
        save_file({k: v.contiguous() for k, v in model.state_dict().items()}, snap / "model.safetensors")
        size = spec.tiny_input_size or spec.input_size
        (snap / "config.json").write_text(json.dumps({
            "architecture": spec.timm_name.split(".")[0], "num_classes": 0,
            "num_features": int(model.num_features), "model_args": dict(spec.tiny_kwargs),
            "pretrained_cfg": {"input_size": [3, size, size], "mean": list(spec.mean),
                               "std": list(spec.std)},
        }, indent=2))


def write_libero(hub_cache: Path, suites=PAPER_SUITES) -> None:
    """lerobot/libero_<suite>_image in the hub cache (where `hf download --repo-type dataset`
    puts it): the generated LIBERO-format suites, LeRobot v3.0 layout."""
    from bench.suites import libero, synthetic

    for name in suites:
        snap = snapshot_dir(hub_cache, libero.LIBERO_REPO_IDS[name], libero.LIBERO_REVISIONS.get(name),
                            repo_type="dataset")
        shutil.copytree(synthetic.tiny_suite_path(name), snap, dirs_exist_ok=True)


def build(root: Path) -> dict[str, str]:
    """Build the world under `root` (idempotent: a finished one is reused); returns the env vars
    that point LeRobot and huggingface_hub at it."""
    root = Path(root)
    env = {"HF_HOME": str(root), "HF_HUB_CACHE": str(root / "hub"),
           "HF_LEROBOT_HOME": str(root / "lerobot"), "HF_HUB_OFFLINE": "1"}
    done = root / "graftbench_hubworld.json"
    if done.is_file():
        return env
    hub_cache = root / "hub"
    write_libero(hub_cache)
    write_timm_weights(hub_cache)
    write_smolvla_base(hub_cache)
    write_pi05_base(hub_cache)
    write_pi0_base(hub_cache)
    (root / "lerobot").mkdir(parents=True, exist_ok=True)
    done.write_text(json.dumps(env, indent=2))
    return env


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m bench.hubworld DIR")
    for key, value in build(Path(sys.argv[1])).items():
        print(f"export {key}={value}")
