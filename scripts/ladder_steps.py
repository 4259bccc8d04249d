"""Per size of the tiny ladder (backbones/tiny_sizes.py): its parameters, token grid and LM width,
and the CPU and wall seconds of one native training step (everything trains, AdamW, clipping) and
one graft step (the backbone frozen, a trainable projector's tokens in place of the tower), at
the recipe's batch (16), two 64 px cameras, chunk 10, one torch thread. Median and minimum of
STEPS steps after one warm-up step; CPU seconds are what an idle core would take, wall seconds
what this machine's load made of them.

    OMP_NUM_THREADS=1 python scripts/ladder_steps.py [NAME ...]   (default: every size)

Prints one JSON line per size (studies/family_scale/README.md, "The ladder").
"""

from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # this checkout's, run as a file
from backbones import adapter_module  # noqa: E402
from backbones.tiny_sizes import SIZES, build_args  # noqa: E402
from tests.backbone_data import CAMERAS, make_stats  # noqa: E402

BATCH, CHUNK, STEPS = 16, 10, 6
TASK = "pick up the black bowl between the plate and the ramekin and place it on the plate"


def raw_batch(generator: torch.Generator) -> dict:
    raw = {key: torch.rand(BATCH, 3, 64, 64, generator=generator) for key in CAMERAS}
    raw["observation.state"] = torch.randn(BATCH, 8, generator=generator)
    raw["action"] = torch.randn(BATCH, CHUNK, 7, generator=generator) * 0.3
    raw["action_is_pad"] = torch.zeros(BATCH, CHUNK, dtype=torch.bool)
    raw["task"] = [TASK] * BATCH
    return raw


def timed(step) -> dict:
    """Median and minimum CPU seconds and median wall seconds of STEPS calls after a warm-up."""
    runs = []
    for i in range(STEPS + 1):
        wall, cpu = time.perf_counter(), time.process_time()
        step()
        if i:
            runs.append((time.perf_counter() - wall, time.process_time() - cpu))
    return {"cpu_med": statistics.median(c for _, c in runs), "cpu_min": min(c for _, c in runs),
            "wall_med": statistics.median(w for w, _ in runs)}


def measure(name: str) -> dict:
    backbone = adapter_module(name).build_tiny_policy(make_stats(), CAMERAS, chunk_size=CHUNK,
                                                      **build_args(name))
    policy, g = backbone.policy, torch.Generator().manual_seed(0)

    def loss():
        batch = backbone.preprocess(raw_batch(g))
        noise = torch.randn(BATCH, CHUNK, backbone.info.max_action_dim, generator=g)
        return backbone.loss(batch, noise, backbone.sample_time(BATCH, g)).mean()

    policy.train()
    for p in policy.parameters():
        p.requires_grad_(True)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-4)

    def native_step():
        optimizer.zero_grad()
        loss().backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
        optimizer.step()

    native = timed(native_step)
    backbone.freeze()
    rows, cols = backbone.info.native_grid
    projector = torch.nn.Linear(384, backbone.info.lm_width)
    features = torch.randn(BATCH, rows * cols, 384)
    projector_optimizer = torch.optim.AdamW(projector.parameters(), lr=1e-3)

    def graft_step():
        with backbone.image_embedder(lambda image: projector(features[: image.shape[0]])):
            value = loss()
        projector_optimizer.zero_grad()
        value.backward()
        projector_optimizer.step()

    return {"params": sum(p.numel() for p in policy.parameters()),
            "grid": backbone.info.native_grid, "lm_width": backbone.info.lm_width,
            "native": native, "graft": timed(graft_step)}


def main(argv: list[str]) -> None:
    """Every name checked before the first size is built: a wrong one is one line, exit 4, in
    the registries' one refusal shape (bench.table)."""
    from bench.option_values import refuse
    from bench.table import Table

    sizes = Table("ladder size", "sizes (none: all)")
    sizes.update(SIZES)
    for name in argv:
        if name not in sizes:
            refuse("scripts/ladder_steps.py", f"NAME: {sizes.refusal(name)}")
    torch.set_num_threads(1)
    for name in argv or list(SIZES):
        print(name, json.dumps(measure(name)), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
