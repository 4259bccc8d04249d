"""The robustness tier in closed loop (`--robustness KINDS` with `--rollouts N`, sim profile): a
cell's policy rolled out in LIBERO with every rendered frame perturbed (the offline table,
bench.robust.perturbations) before the policy or its encoder sees it. Only native and the best
graft (lowest clean MSE) roll out: each perturbation costs as much as the cell's clean rollouts.

Paired with the clean rollouts episode by episode: the same spec, so the same init states and env
seeds (bench.sim.rollout). What a perturbation draws (a noise field, a shift direction, a patch
position) is fixed per rendered frame: seeded by a hash of the frame's pixels, as offline it is
seeded by the window. A frame, and so an episode, is the same in every rerun: deterministic per
episode and seed; severity 0 returns the frames as they are (the clean rollout's very actions).
"""

from __future__ import annotations

import hashlib

import torch
from torch import Tensor

from bench.grid.cells import CellSpec, graft_cells
from bench.grid.kinds import GRAFT, NATIVE
from bench.cell.rollouts import (LoopGraft, cell_rollouts, policy_fingerprint,
                                 policy_identity)
from bench.robust.perturbations import Applied

# The cells that roll out under perturbations (besides the best graft): the released policy.
LOOP_KINDS = (NATIVE,)


def frame_ids(images: dict[str, Tensor]) -> Tensor:
    """(B,) int64: one id per observation row, from the bytes of its frames (every camera): the
    key of what a perturbation draws for that frame (Applied.images' `frames`)."""
    cameras = sorted(images)
    rows = next(iter(images.values())).shape[0]
    ids = []
    for b in range(rows):
        digest = hashlib.sha256()
        for camera in cameras:
            digest.update(images[camera][b].detach().float().cpu().contiguous().numpy().tobytes())
        ids.append(int(digest.hexdigest()[:12], 16))
    return torch.tensor(ids, dtype=torch.long)


def perturb_frames(applied: Applied):
    """images {camera: (B, 3, H, W) in [0, 1]} -> the same under `applied` (cell_act's perturb)."""
    def perturb(images: dict[str, Tensor]) -> dict[str, Tensor]:
        return applied.images(images, frame_ids(images))

    return perturb


def best_graft_encoder(profile, store, backbone: str, suite: str) -> str | None:
    """The run's graft encoder with the lowest clean normalised MSE (mean over its stored seeds)
    on `backbone` x `suite`; ties by name; None when no graft is stored."""
    errors: dict[str, list[float]] = {}
    for cell in graft_cells(profile):
        if (cell.backbone, cell.suite) != (backbone, suite):
            continue
        record = store.load(cell.id)
        if record is not None:
            errors.setdefault(cell.encoder, []).append(record.scores.mse_in())
    if not errors:
        return None
    return min(errors, key=lambda e: (sum(errors[e]) / len(errors[e]), e))


def rolls_out(cell: CellSpec, profile, store) -> bool:
    """Whether `cell`'s robustness case rolls out: native, and the best graft's cells."""
    if cell.kind in LOOP_KINDS:
        return True
    return cell.kind == GRAFT and cell.encoder == best_graft_encoder(profile, store,
                                                                     cell.backbone, cell.suite)


def log_id(cell: CellSpec, applied: Applied) -> str:
    """The episode log of a cell's rollouts under `applied` (never its clean rollouts' log)."""
    return f"{cell.id}@{applied.kind}-{applied.severity}"


def rollouts_under(applied: Applied, cell: CellSpec, ws, scorer, record, episodes: int, *,
                   scenes=None) -> dict:
    """The cell's policy (scorer: bench.robust.rescore's, rebuilt from its stored projector) rolled
    out `episodes` per task with every frame under `applied`; run_rollouts' dict plus "spec" and
    "perturbation". Resumable per episode through the store's episode log."""
    identity = policy_identity(record.measured, perturbation=applied.to_json())
    name = log_id(cell, applied)
    graft = (LoopGraft(scorer.feed, scorer.inputs.encoder, scorer.inputs.grid)
             if scorer.feed is not None else None)
    out = cell_rollouts(cell, scorer.suite, scorer.backbone, episodes, graft=graft,
                        progress=ws.progress, store=ws.store, scenes=scenes,
                        batching=ws.rollout_batching,
                        perturb=perturb_frames(applied), log_id=name,
                        policy=policy_fingerprint(scorer.backbone, scorer.feed, identity))
    ws.store.episode_log(name, "").clear()  # the robustness record holds them now
    return {"perturbation": applied.to_json(), **out}


def has_rollouts(stored: dict | None, applied: Applied, episodes: int) -> bool:
    """A stored entry of RobustRecord.rollouts is this perturbation at `episodes` per task."""
    return (stored is not None and stored.get("perturbation") == applied.to_json()
            and stored.get("spec", {}).get("episodes_per_task") == episodes)
