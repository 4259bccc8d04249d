"""Plan, then run: what one cell needs, decided before anything runs.

`plan(cell, store, run, ...)` is pure (it reads the store, writes nothing): it says whether the
stored record stands for this run (resume) or the cell is measured, and with what `CellContext`:
the features mode, a planted feature transform (--degrade-encoder), and the trained projector of
its graft the cell takes instead of training the same one again. It is handed the stored record
(the service reads it once). The runner measures with that context and returns what it measured
(`CellResult`); the service writes it and keeps the projector for later plans. No cell state
lives on the workspace (its resources only: policies, suites, encoders, features).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Mapping

from bench.grid.cells import CellSpec
from bench.grid.kinds import GRAFT
from bench.results.current import RunConditions, fewer_episodes, is_current
from bench.results.record import Record, checkpoint_revision

FEATURES_MODES = ("cache", "loop")


@dataclass(frozen=True)
class TrainedProjector:
    """A trained projector kept for the session (its weights on disk: a paper grid trains hundreds
    of projectors of up to ~10 MB each), with what its training recorded."""

    path: Path
    curve: list
    probe_losses: dict
    cell_id: str


def shared_projector_key(cell: CellSpec, features_mode: str) -> tuple | None:
    """Key of the projector a cell trains when its graft trains exactly the same one (the kind
    table says which: bench.grid.kinds `shares_graft_training`). None for every other cell."""
    if features_mode != "cache" or not cell.spec.shares_graft_training(cell.encoder, cell.variant):
        return None
    graft = cell if cell.kind == GRAFT else cell.reference
    return (graft.id, features_mode)


@dataclass(frozen=True)
class CellContext:
    """What one cell is measured with, beyond the workspace's shared resources."""

    features_mode: str = "cache"  # "cache" (pooled features stored once) or "loop"
    # features {camera: (B, T, C)}, rows -> same: a planted degradation (--degrade-encoder,
    # tests); recorded as the record's feature_transform, never shared, never resumed.
    feature_transform: Callable | None = None
    reuse: TrainedProjector | None = None  # the graft's trained projector this cell takes
    keep_as: tuple | None = None  # key the cell's trained projector is handed back under

    def __post_init__(self) -> None:
        if self.features_mode not in FEATURES_MODES:
            raise ValueError(f"features_mode {self.features_mode!r} not in {FEATURES_MODES}")


@dataclass(frozen=True)
class CellResult:
    """What measuring a cell gave: its record, not yet written, and its graft's projector (a
    torch module: the service saves it beside the record, and keeps it for a later cell of the
    session under `CellContext.keep_as`); `stored`: the record is already in the store (a job
    array's task wrote it)."""

    record: Record
    projector: object | None = None
    stored: bool = False


def cell_context(cell: CellSpec, features_mode: str = "cache", *,
                 projectors: Mapping[tuple, TrainedProjector] | None = None,
                 feature_transform: Callable | None = None) -> CellContext:
    """The context to measure `cell` with: the graft's projector when one was kept. A cell that
    tunes its encoder runs it in the loop whatever the run's mode (stored features are the
    frozen encoder's), and so does its live twin (its question is how the loop differs)."""
    if cell.spec.encoder_in_loop:
        features_mode = "loop"
    share = shared_projector_key(cell, features_mode) if feature_transform is None else None
    reuse = (projectors or {}).get(share) if share is not None and cell.kind != GRAFT else None
    return CellContext(features_mode, feature_transform, reuse,
                       keep_as=share if reuse is None else None)


@dataclass(frozen=True)
class CellPlan:
    """Resume `cell` from `resume`, roll out the episodes `extend` lacks (bench.cell.extend), or
    measure it with `context` (after discarding the stored record when `discard`: a planted
    degradation must never outlive its run)."""

    cell: CellSpec
    context: CellContext
    resume: Record | None = None
    discard: bool = False
    extend: Record | None = None

    def work(self, steps: int) -> str:
        """What measuring does, for the start line."""
        if not self.cell.trains_projector:
            return "no training,"
        if self.context.reuse is not None:
            return "its graft's trained projector, then"
        trained = "projector + encoder" if self.cell.spec.tune_encoder else "projector"
        return f"{self.cell.spec.scaled_steps(steps, self.cell.variant)} {trained} steps, then"


def plan(cell: CellSpec, stored: Record | None, run: RunConditions, *,
         workspace: Callable[[], object] | None = None,
         rerun: bool = False, features_mode: str = "cache",
         projectors: Mapping[tuple, TrainedProjector] | None = None,
         feature_transform: Callable | None = None,
         rebuilds: Callable[[CellSpec, Record], bool] = lambda cell, record: False) -> CellPlan:
    """Resume, extend or measure `cell`, whose stored record is `stored` (None: none readable).
    `run`: the conditions a stored record must match (bench.results.current); `workspace()`:
    the (lazy) workspace the conditions that need the policy are looked up in (revision,
    normalizer_fingerprint: `on_weights`), asked only when the stored record passes `run` but
    perhaps its episode count (None: not looked up). A record that
    passes all but holds fewer episodes per task is extended when `rebuilds(cell, stored)` (its
    policy can be rebuilt from the store: bench.cell.extend.rebuilds_policy)."""
    context = cell_context(cell, features_mode, projectors=projectors,
                           feature_transform=feature_transform)
    degraded = stored is not None and (feature_transform is not None
                                       or stored.measured.feature_transform is not None)
    if rerun or stored is None or degraded:
        return CellPlan(cell, context, discard=degraded)
    if not is_current(stored, replace(run, rollouts=0)):
        return CellPlan(cell, context)
    full = on_weights(run, cell, workspace()) if workspace is not None else run
    if is_current(stored, full):
        return CellPlan(cell, context, resume=stored)
    if fewer_episodes(stored, full) and rebuilds(cell, stored):
        return CellPlan(cell, context, extend=stored)
    return CellPlan(cell, context)


def on_weights(run: RunConditions, cell: CellSpec, ws) -> RunConditions:
    """`run` with the weights and normaliser `cell` is measured on, as the workspace `ws` lends
    them (loads the policy)."""
    where = (cell.backbone, cell.suite, cell.release)
    return replace(run, revision=checkpoint_revision(ws.checkpoint(*where)),
                   normalizer_fingerprint=ws.normalizer(*where).fingerprint)
