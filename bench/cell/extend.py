"""More closed-loop episodes for a stored cell: `--rollouts N` on a record that holds fewer.

Episode e of a task is the same init state and env seed whatever the number of episodes per task
(bench.sim.rollout), so a record's n episodes per task are the first n of any larger count. A
stored record that stands for the run in everything but its episode count (the same protocol,
weights and normaliser: bench.results.current) keeps its scores, its training and its episodes;
only the missing episodes are rolled out, by the policy rebuilt from the record (the released
policy, its stored projector checked by sha256, the encoder). Nothing is trained or scored again:
a sequential closed-loop study (bench.analysis.sequential_study) grows an item's episodes round
by round at the cost of its new episodes.

Only cells whose policy the record rebuilds extend: not LoRA (its adapters are not stored), not
an encoder in the loop (a tuned encoder's weights are not stored); those are measured again.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from bench.cell.plan import CellResult
from bench.cell.projectors import ProjectorFileError, load_projector
from bench.grid.cells import CellSpec
from bench.results.record import Record
from graftcore.graft import GraftFeed, Projector


def rebuilds_policy(cell: CellSpec, record: Record, results_dir: str | Path) -> bool:
    """Can `record`'s policy be rebuilt for more episodes: a kind without LoRA or an encoder in
    the loop, and its projector file present when it trains one (its sha256 is checked when
    read)."""
    kind = cell.spec
    if kind.lora or kind.encoder_in_loop:
        return False
    if not cell.trains_projector:
        return True
    file = record.training.projector_file
    return bool(file and record.training.projector_sha256
                and (Path(results_dir) / file).is_file())


def stored_episodes(record: Record) -> tuple[list[dict], int]:
    """(the record's episodes, its episodes per task); ([], 0) when it holds none."""
    rollouts = record.run.rollouts or {}
    if not rollouts.get("episodes"):
        return [], 0
    return list(rollouts["episodes"]), int(rollouts["spec"]["episodes_per_task"])


def rebuilt_graft(cell: CellSpec, ws, backbone, inputs, record: Record):
    """The LoopGraft of a cell that trains a projector, from its stored projector (None for a
    cell that trains none: the released policy samples as is)."""
    from bench.cell.rollouts import LoopGraft

    if not cell.trains_projector:
        return None
    state = load_projector(ws.store.root, cell.id, record.training.projector_file,
                           record.training.projector_sha256)
    projector = Projector(int(state["linear.weight"].shape[1]), backbone.info.lm_width)
    projector.load_state_dict(state)
    projector = projector.to(inputs.device).eval()
    tower = backbone.native_tower_grid if inputs.tower else None
    feed = GraftFeed(projector, backbone.camera_keys, inputs.grid, tower=tower)
    encoder = None if inputs.tower else ws.encoder(cell.encoder)
    return LoopGraft(feed, encoder, inputs.grid)


def extend_rollouts(cell: CellSpec, ws, stored: Record, *, scenes=None) -> CellResult:
    """`stored` with its episodes grown to `ws.rollouts` per task: the stored ones kept, the
    rest rolled out by the rebuilt policy (resumable per episode, as a measured cell's are);
    its scores and training untouched. `scenes`: a test's stand-in for LIBERO."""
    from bench.cell.rollouts import cell_rollouts, policy_fingerprint, policy_identity
    from bench.cell.runner import cell_inputs

    t0 = time.perf_counter()
    _, per_task = stored_episodes(stored)
    suite, split = ws.suite(cell.suite), ws.split(cell.suite)
    backbone = ws.backbone(cell.backbone, cell.suite, cell.release)
    device = next(backbone.policy.parameters()).device
    inputs = cell_inputs(cell, ws.profile.protocol, suite, split, backbone, device)
    try:
        graft = rebuilt_graft(cell, ws, backbone, inputs, stored)
    except ProjectorFileError as e:
        raise RuntimeError(f"{cell.id}: cannot extend its rollouts: {e}") from None
    feed = graft.feed if graft is not None else None
    rollouts = cell_rollouts(
        cell, suite, backbone, ws.rollouts, store=ws.store, progress=ws.progress, graft=graft,
        batching=ws.rollout_batching, scenes=scenes, kept=stored.run.rollouts,
        policy=policy_fingerprint(backbone, feed, policy_identity(stored.measured)))
    rollouts["settings"]["extended_from"] = per_task
    spent = time.perf_counter() - t0
    earlier = stored.run.timings_s
    added = dict(rollouts=spent, total=spent)  # the phases' timings_s entries grow by it
    timings = {**earlier, **{k: round(earlier.get(k, 0.0) + v, 3) for k, v in added.items()}}
    run = replace(stored.run, rollouts=rollouts, timings_s=timings)
    return CellResult(replace(stored, run=run))
