"""GPU smoke of a graft on real-size, randomly initialised SmolVLA and pi0.5.

Per backbone: build the architecture offline (no weights, no hub), then a few projector steps of a
graft and one evaluation batch, in bf16 autocast on CUDA (bench.loops.train.frozen_autocast),
through the harness's own pieces: the adapter's `preprocess`, `sample_time`, `image_embedder`,
`loss` and `sample_actions` (via bench.loops.evaluate.sample_grafted), graftcore.graft's Projector
and GraftFeed, and bench.resources.features.pool_grid. Prints one JSON line and one human line per
backbone.

- Architectures: SmolVLA from SmolVLM2-500M's config numbers (backbones.tiny_smolvla.REAL_VLM,
  16 of 32 text layers as smolvla_base: 450M parameters); pi0.5 from LeRobot's default
  PI05Config (gemma_2b VLM, gemma_300m expert, 224 px SigLIP: 4.14B parameters as built, the
  unused 257k-row expert output layer included). Weights stay float32 (1.7 and 15.4 GiB), as the
  harness runs real checkpoints (load_policy keeps float32) with bf16 autocast on top: the smoke
  checks that configuration. Autocast keeps the bf16 copies of frozen weights that backward
  needs, so expect a pi0.5 peak near 25 GiB: far inside an H200's 139 GiB.
- Text: the policies' OWN pre-processors run on raw batches, with local word-level tokenizers
  in place of the hub ones (SmolVLA: the real-shape SmolVLM folder; pi0.5: the tiny PaliGemma
  tokenizer, ids < 300 of the real 257152-row embedding; prompts padded to the real 200 tokens).
- Encoder: a random (B, C, 2h, 2w) grid on the device (C=768, SigLIP-B's width) stands in for
  an encoder's output and is pooled to the backbone's native grid (8x8 SmolVLA, 16x16 pi0.5).
- Devices: raw batches start on the CPU and flow-matching noise/time are drawn from a CPU
  generator, exactly as bench.loops.train.fit does; moving them is the adapters' and processors'
  job, so a device bug there fails this smoke. Sampling noise is moved here, as
  bench.loops.evaluate.score does.

`--dry-run` runs the same code on the CPU with the tiny builds (build_tiny_policy).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import resource
import sys
import time
import traceback
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # run as a file; the GPU machine has no editable install
    sys.path.insert(0, str(REPO_ROOT))
# Nor of the LeRobot plugin, whose graft wrapper, encoder and families graftbench imports.
PLUGIN_ROOT = REPO_ROOT / "plugins" / "lerobot_policy_graft"
if str(PLUGIN_ROOT) not in sys.path:
    sys.path.insert(1, str(PLUGIN_ROOT))

BACKBONES = ("smolvla", "pi05")
CAMERAS = ("observation.images.image", "observation.images.wrist_image")  # LIBERO's
STATE_DIM, ACTION_DIM = 8, 7  # LIBERO's
TASKS = ("pick up the black bowl and place it on the plate", "open the top drawer of the cabinet")
# Raw camera size: LIBERO's 256 px for the real builds (each policy resizes it itself), the
# tiny towers' 64 px for the dry run.
RAW_IMAGE_SIDE = {"real": 256, "tiny": 64}
TINY_CHUNK = 10


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import torch

    if not args.dry_run and not torch.cuda.is_available():
        print(
            f"gpu_smoke: refused: CUDA is not available (torch {torch.__version__}, "
            f"CUDA build {torch.version.cuda}); run it on a CUDA machine, or pass --dry-run "
            "for the same code path on the CPU with the tiny architectures",
            file=sys.stderr,
        )
        return 2
    device = torch.device("cpu" if args.dry_run else "cuda")
    size = args.size or ("tiny" if args.dry_run else "real")
    failures = 0
    for name in args.backbones:
        try:
            record = smoke_one(name, size, device, args)
        except Exception as error:  # report it and go on: the other backbone still tells a lot
            traceback.print_exc(file=sys.stderr)
            record = {"smoke": "gpu_smoke", "backbone": name, "size": size, "ok": False,
                      "device": str(device), "error": f"{type(error).__name__}: {error}"[:2000]}
        failures += not record["ok"]
        print(json.dumps(record, sort_keys=True), flush=True)
        print(human_line(record), flush=True)
        gc.collect()
        if device.type == "cuda":
            torch.cuda.empty_cache()
    return 1 if failures else 0


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dry-run", action="store_true",
                        help="CPU, tiny architectures (no CUDA, no wheelhouse needed)")
    parser.add_argument("--size", choices=("real", "tiny"), default=None,
                        help="architecture size (default: real on CUDA, tiny with --dry-run)")
    parser.add_argument("--backbones", type=lambda s: s.split(","), default=list(BACKBONES),
                        help=f"comma-separated, from {','.join(BACKBONES)}")
    parser.add_argument("--steps", type=int, default=5, help="projector training steps")
    parser.add_argument("--batch-size", type=int, default=2)
    parser.add_argument("--channels", type=int, default=768,
                        help="encoder channels of the random feature grid (768: SigLIP-B)")
    args = parser.parse_args(argv)
    unknown = [b for b in args.backbones if b not in BACKBONES]
    if unknown:
        parser.error(f"unknown backbone(s) {unknown}; choose from {list(BACKBONES)}")
    if args.steps < 2:
        parser.error(f"--steps {args.steps}: at least 2 (the first step includes warm-up)")
    return args


# -- one backbone ---------------------------------------------------------------------------
def smoke_one(name: str, size: str, device, args: argparse.Namespace) -> dict:
    """Build, `args.steps` projector steps, one sampled batch; the JSON record of it."""
    import torch

    from bench.loops.evaluate import sample_grafted
    from bench.cell.freeze import assert_only_trainable, trainable_parameters
    from graftcore.graft import GraftFeed, Projector
    from bench.loops.train import frozen_autocast

    torch.manual_seed(0)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    started = time.perf_counter()
    backbone = build_backbone(name, size, device)
    backbone.freeze()
    _sync(device)
    build_s = time.perf_counter() - started
    policy_device = next(backbone.policy.parameters()).device
    if policy_device.type != device.type:
        raise RuntimeError(f"the {name} policy is on {policy_device}, expected {device}")
    weights_gib = _allocated_gib(device)

    info = backbone.info
    batch_size = args.batch_size
    projector = Projector(args.channels, info.lm_width).to(device)
    feed = GraftFeed(projector, backbone.camera_keys, info.native_grid)
    assert_only_trainable(trainable_parameters(projector), backbone.policy, projector)
    out_dtypes: set[str] = set()
    projector.register_forward_hook(lambda _m, _i, out: out_dtypes.add(str(out.dtype)))
    optimizer = torch.optim.AdamW(projector.parameters(), lr=1e-3)
    before = projector.linear.weight.detach().clone()
    noise_gen = torch.Generator().manual_seed(0)  # CPU, as bench.loops.train.fit draws noise and time
    raw = raw_batch(batch_size, info.chunk_size, RAW_IMAGE_SIDE[size], seed=0)
    noise_shape = (batch_size, info.chunk_size, info.max_action_dim)

    losses, step_s = [], []
    for step in range(args.steps):
        _sync(device)
        tick = time.perf_counter()
        batch = backbone.preprocess(raw)
        if step == 0:
            check_on_device(batch, device)
        features = random_features(backbone.camera_keys, batch_size, args.channels,
                                   info.native_grid, device, seed=step)
        noise = torch.randn(noise_shape, generator=noise_gen)
        flow_time = backbone.sample_time(batch_size, noise_gen)
        if step == 0:
            caller_devices = {"raw_batch": str(raw["observation.state"].device),
                              "loss_noise": str(noise.device), "loss_time": str(flow_time.device),
                              "features": str(features[backbone.camera_keys[0]].device)}
        feed.bind(features)
        with backbone.image_embedder(feed), frozen_autocast(device):
            loss = backbone.loss(batch, noise, flow_time).mean()
        feed.assert_consumed()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))  # synchronises
        _sync(device)
        step_s.append(time.perf_counter() - tick)
    train_peak = _peak_gib(device)
    grad = projector.linear.weight.grad
    moved = float((projector.linear.weight.detach() - before).abs().max())

    eval_noise = torch.randn(noise_shape, generator=noise_gen)
    features = random_features(backbone.camera_keys, batch_size, args.channels, info.native_grid,
                               device, seed=1000)
    _sync(device)
    tick = time.perf_counter()
    batch = backbone.preprocess(raw)
    actions = sample_grafted(backbone, batch, eval_noise.to(device), feed, features)
    _sync(device)
    sample_s = time.perf_counter() - tick

    record = {
        "smoke": "gpu_smoke",
        "backbone": name,
        "size": size,
        "device": str(policy_device),
        "device_name": (torch.cuda.get_device_name(device) if device.type == "cuda"
                        else platform.processor() or "cpu"),
        "autocast": "bf16" if device.type == "cuda" else "off",
        "projector_out_dtypes": sorted(out_dtypes),
        "param_dtypes": sorted({str(p.dtype) for p in backbone.policy.parameters()}),
        "policy_params": sum(p.numel() for p in backbone.policy.parameters()),
        "projector_params": trainable_parameters(projector),
        "enc_channels": args.channels,
        "native_grid": list(info.native_grid),
        "lm_width": info.lm_width,
        "chunk_size": info.chunk_size,
        "batch_size": batch_size,
        "text": "policy pre-processor with a local word-level tokenizer",
        "caller_devices": {**caller_devices, "sample_noise": str(device)},
        "steps": len(losses),
        "losses": losses,
        "loss_finite": all(math.isfinite(v) for v in losses),
        "projector_grad_finite": grad is not None and bool(torch.isfinite(grad).all()),
        "projector_moved": moved > 0,
        "build_s": round(build_s, 3),
        "sec_per_step": [round(s, 4) for s in step_s],
        "sec_per_step_after_first": round(sorted(step_s[1:])[len(step_s[1:]) // 2], 4),
        "sample_s": round(sample_s, 4),
        "denoise_steps": info.num_denoise_steps,
        "sampled_shape": list(actions.shape),
        "sampled_device": str(actions.device),
        "sampled_finite": bool(torch.isfinite(actions).all()),
        "weights_gib": weights_gib,
        "peak_train_gib": train_peak,
        "peak_cuda_mem_gib": _peak_gib(device),
        "max_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
        "versions": versions(),
    }
    record["ok"] = bool(
        record["loss_finite"] and record["projector_grad_finite"] and record["projector_moved"]
        and record["sampled_finite"] and actions.device.type == device.type
        and list(actions.shape) == [batch_size, info.chunk_size, ACTION_DIM]
    )
    del backbone, batch, feed, projector, optimizer, actions
    return record


def build_backbone(name: str, size: str, device):
    """The adapter around a random-init policy of the given size, on `device`."""
    stats = dataset_stats()
    if size == "tiny":
        if name == "smolvla":
            from backbones.smolvla import build_tiny_policy

            return build_tiny_policy(stats, CAMERAS, chunk_size=TINY_CHUNK, device=str(device))
        from backbones.pi05 import build_tiny_policy

        backbone = build_tiny_policy(stats, CAMERAS, chunk_size=TINY_CHUNK)
        if device.type != "cpu":
            raise RuntimeError("backbones.pi05.build_tiny_policy builds on the CPU only")
        return backbone
    return (build_real_smolvla if name == "smolvla" else build_real_pi05)(stats, device)


def build_real_smolvla(stats: dict, device):
    """smolvla_base's architecture (SmolVLM2-500M numbers, 16 text layers), random weights."""
    import torch
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from backbones.smolvla import SmolVLABackbone
    from backbones.tiny_smolvla import libero_smolvla_config, real_shape_vlm_folder

    side = RAW_IMAGE_SIDE["real"]
    config = libero_smolvla_config(
        CAMERAS, (3, side, side), STATE_DIM, ACTION_DIM,
        vlm_model_name=str(real_shape_vlm_folder()), num_vlm_layers=16, device=device.type,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        policy = SmolVLAPolicy(config)  # load_vlm_weights=False: random weights, float32
    policy.to(device).eval()  # as backbones.smolvla.build_tiny_policy does
    preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
    return SmolVLABackbone(policy, preprocessor, postprocessor)


def build_real_pi05(stats: dict, device):
    """LeRobot's default PI05Config (gemma_2b + gemma_300m, 224 px), random float32 weights."""
    import torch
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot.policies.pi05.configuration_pi05 import PI05Config
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    from backbones.pi05 import PI05Backbone
    from backbones.tiny_paligemma import TOKENIZER_DIRNAME, ensure_tiny_tokenizer, local_tokenizer
    from ondisk.paths import cache_dir

    side = RAW_IMAGE_SIDE["real"]
    inputs = {key: PolicyFeature(FeatureType.VISUAL, (3, side, side)) for key in CAMERAS}
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (STATE_DIM,))
    config = PI05Config(
        input_features=inputs,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
        device=device.type,  # PI05Policy.__init__ moves its model there (modeling_pi05.py:742)
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        policy = PI05Policy(config)
    policy.eval()
    with local_tokenizer(ensure_tiny_tokenizer(cache_dir() / TOKENIZER_DIRNAME)):
        preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
    return PI05Backbone(policy, preprocessor, postprocessor, CAMERAS)


# -- inputs and checks ----------------------------------------------------------------------
def dataset_stats() -> dict:
    """Stats for both normalisers (SmolVLA: mean/std; pi0.5: quantiles), LIBERO's widths."""
    import numpy as np

    def one(dim: int, scale: float) -> dict:
        spread = np.linspace(0.5, 2.0, dim) * scale
        return {"mean": np.zeros(dim), "std": spread / 2, "min": -spread * 1.5,
                "max": spread * 1.5, "q01": -spread, "q99": spread}

    stats = {"observation.state": one(STATE_DIM, 1.0), "action": one(ACTION_DIM, 0.5)}
    for camera in CAMERAS:  # present as in LeRobot datasets; both policies' VISUAL is IDENTITY
        stats[camera] = {"mean": np.full((3, 1, 1), 0.5), "std": np.full((3, 1, 1), 0.25)}
    return stats


def raw_batch(batch_size: int, chunk: int, side: int, seed: int) -> dict:
    """A raw batch (backbones.base) on the CPU: images in [0, 1], one padded chunk step."""
    import torch

    gen = torch.Generator().manual_seed(seed)
    raw = {key: torch.rand(batch_size, 3, side, side, generator=gen) for key in CAMERAS}
    raw["observation.state"] = torch.randn(batch_size, STATE_DIM, generator=gen)
    raw["action"] = torch.randn(batch_size, chunk, ACTION_DIM, generator=gen) * 0.3
    raw["action_is_pad"] = torch.zeros(batch_size, chunk, dtype=torch.bool)
    raw["action_is_pad"][0, -1] = True  # the masking paths run too
    raw["task"] = [TASKS[i % len(TASKS)] for i in range(batch_size)]
    return raw


def random_features(cameras, batch_size: int, channels: int, grid, device, seed: int) -> dict:
    """{camera: (B, rows*cols, C) float32 on `device`}: a random (B, C, 2*rows, 2*cols) encoder
    grid pooled to the native grid by bench.resources.features.pool_grid, as an in-loop encoder gives."""
    import torch

    from bench.resources.features import pool_grid

    gen = torch.Generator(device=device).manual_seed(seed)
    rows, cols = grid
    return {
        camera: pool_grid(
            torch.randn(batch_size, channels, 2 * rows, 2 * cols, generator=gen, device=device),
            (rows, cols),
        )
        for camera in cameras
    }


def check_on_device(batch: dict, device) -> None:
    """Every tensor of the prepared batch must be on `device`: the pre-processor moves them."""
    import torch

    stray = {k: str(v.device) for k, v in batch.items()
             if isinstance(v, torch.Tensor) and v.device.type != device.type}
    if stray:
        raise RuntimeError(f"the pre-processor left {stray} off {device}")


def versions() -> dict:
    import lerobot
    import torch
    import transformers

    return {"python": platform.python_version(), "torch": torch.__version__,
            "transformers": transformers.__version__, "lerobot": lerobot.__version__,
            "torch_from": str(Path(torch.__file__).parent.parent)}


def human_line(record: dict) -> str:
    if not record["ok"] and "error" in record:
        return f"[gpu_smoke] {record['backbone']} ({record['size']}) FAILED: {record['error']}"
    peak = record["peak_cuda_mem_gib"]
    memory = (f"peak CUDA {peak:.2f} GiB" if peak is not None
              else f"max RSS {record['max_rss_gib']} GiB")
    return (
        f"[gpu_smoke] {record['backbone']} ({record['size']}, {record['policy_params'] / 1e6:.1f}M "
        f"params, {record['device']}, autocast {record['autocast']}): "
        f"{'ok' if record['ok'] else 'FAILED CHECKS'}; {record['steps']} steps, "
        f"{record['sec_per_step_after_first']:.3f} s/step after the first "
        f"({record['sec_per_step'][0]:.2f} s), loss {record['losses'][0]:.4f} -> "
        f"{record['losses'][-1]:.4f}; sample {record['sample_s']:.3f} s "
        f"{tuple(record['sampled_shape'])}; build {record['build_s']:.1f} s; {memory}"
    )


def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _allocated_gib(device) -> float | None:
    import torch

    return round(torch.cuda.memory_allocated(device) / 2**30, 3) if device.type == "cuda" else None


def _peak_gib(device) -> float | None:
    import torch

    if device.type != "cuda":
        return None
    return round(torch.cuda.max_memory_allocated(device) / 2**30, 3)


if __name__ == "__main__":
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # no hub, ever: a hub call fails at once
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    sys.exit(main())
