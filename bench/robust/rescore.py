"""The robustness case of one cell: its stored projector (or the released policy as is) rescored
on perturbed held-out windows, no retraining. Read top to bottom: the cell's stored record ->
its projector from disk -> per perturbation, the perturbed windows' features (through the
feature store, keyed by the perturbation) or images -> the same scorer as the cell -> one
robustness record (bench.results.robust).

Windows: every `WINDOW_STRIDE`-th held-out window of the split (the same for every cell of a
suite), so a case costs a fraction of its cell (docs/PERFORMANCE.md); the clean reference is the
cell record's own per-window errors on those windows (the scorer gives a window the same bits
in any batch: tests/test_robustness.py checks it at severity 0).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from bench.grid.cells import CellSpec
from bench.grid.kinds import GRAFT
from bench.results.record import Record
from bench.results.robust import (RobustEntry, RobustRecord, base_of, load_robust, stamped,
                                  write_robust)
from bench.loops.evaluate import score
from bench.loops.encode import encode_pooled
from bench.progress import Progress, say
from bench.robust.perturbations import Applied
from bench.cell.projectors import ProjectorFileError, load_projector
from bench.cell.runner import cell_inputs
from graftcore.graft import GraftFeed, Projector

WINDOW_STRIDE = 4  # one held-out window in 4 (tiny: 37 of 148 per suite)
# Windows per sampler call: this times the protocol's eval batch (tiny 32 -> 128, fastest of
# 64/128/256 here; paper 16 -> 64). A window gets the same bits in any batch (tested).
EVAL_BATCH_FACTOR = 4


class RobustUnavailable(RuntimeError):
    """The cell has nothing to rescore (no record, no projector): one line with the command."""


def robust_windows(windows: Tensor, stride: int = WINDOW_STRIDE) -> Tensor:
    """(W,) the held-out windows a robustness case scores: every `stride`-th, in split order."""
    return windows[::stride]


@dataclass
class PerturbedWindows:
    """The held-out windows' frames under one perturbation, as a feature store source: row i is
    `windows[i]` (bench.resources.features.FeatureSource)."""

    suite: object
    windows: Tensor
    applied: Applied

    @property
    def name(self) -> str:
        return f"{self.suite.name}[{self.applied.label}]"

    @property
    def camera_keys(self) -> tuple[str, ...]:
        return self.suite.camera_keys

    @property
    def state(self) -> Tensor:
        return self.suite.state[self.windows]

    @property
    def fingerprint(self) -> str:
        """The suite, the windows and the perturbation (parameters, seed, version)."""
        blob = json.dumps({"suite": self.suite.fingerprint, "windows": self.windows.tolist(),
                           "perturbation": self.applied.to_json()}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def images(self, rows: Tensor) -> dict[str, Tensor]:
        frames = self.windows[torch.as_tensor(rows, dtype=torch.long).reshape(-1)]
        return self.applied.images(self.suite.images(frames), frames)


def rerun_hint(cell: CellSpec, results_dir) -> str:
    test = "test_graft" if cell.kind == GRAFT else "test_control"
    return (f"measure it first: pytest bench -k \"{test} and {cell.id}\" --results-dir "
            f"{results_dir} (with this run's other options), then rerun the robustness case")


def stored_cell(cell: CellSpec, ws) -> Record:
    """The cell's stored record; RobustUnavailable naming the command that measures it when it
    is missing."""
    record = ws.store.load(cell.id)
    if record is None:
        raise RobustUnavailable(f"{cell.id}: no stored record to rescore under perturbations; "
                                + rerun_hint(cell, ws.store.root))
    return record


def stored_projector(cell: CellSpec, ws, record: Record) -> dict | None:
    """The cell's projector state (None for a cell that trains none), read only when something
    is to be rescored: a complete robustness record resumes from a results folder kept without
    its projectors (a committed study's). RobustUnavailable when it is missing."""
    if not cell.trains_projector:
        return None
    try:
        return load_projector(ws.store.root, cell.id, record.training.projector_file,
                              record.training.projector_sha256)
    except ProjectorFileError as e:
        raise RobustUnavailable(f"{cell.id}: no stored projector to rescore: {e}") from None


def measure_robust(cell: CellSpec, ws, perturbations: tuple[Applied, ...], *,
                   rerun: bool = False, window_stride: int = WINDOW_STRIDE,
                   rollouts: int = 0, scenes=None) -> tuple[RobustRecord, bool]:
    """The robustness record of `cell` under `perturbations` (stored entries of the same
    measurement and windows resumed unless `rerun`), written to the store; (record, measured
    anything). `rollouts` > 0: also rolled out that many episodes per task under each
    perturbation (bench.robust.closed_loop; `scenes`: a test's stand-in for LIBERO)."""
    t_start = time.perf_counter()
    record = stored_cell(cell, ws)
    root = ws.store.root
    windows = robust_windows(ws.split(cell.suite).windows, window_stride)
    stored = None if rerun else load_robust(root, cell.id)
    if stored is not None and not (stored.is_for(record)
                                   and stored.window_ids == windows.tolist()):
        stored = None  # rescored from an earlier measurement of the cell, or other windows
    wanted = [a.to_json() for a in perturbations]
    kept = [e for e in (stored.entries if stored else []) if e.perturbation not in wanted]
    missing = [a for a, key in zip(perturbations, wanted)
               if stored is None or stored.entry(key) is None]
    scorer, fresh = None, {}
    if missing:
        scorer = _Scorer(cell, ws, record, stored_projector(cell, ws, record), windows)
        fresh = dict(zip((a.label for a in missing), scorer.entries(missing)))
    entries = [fresh.get(a.label) or stored.entry(key) for a, key in zip(perturbations, wanted)]
    measured = bool(missing)
    out = RobustRecord(cell.id, cell.kind, cell.backbone, cell.suite, cell.encoder, cell.seed,
                       base_of(record), windows.tolist(), kept + entries,
                       timings_s={"total": round(time.perf_counter() - t_start, 3)},
                       rollouts=dict(stored.rollouts) if stored else {})
    if measured or stored is None or out.entries != stored.entries:
        out = stamped(out)
        write_robust(root, out)
    else:
        out = stored
    for applied in perturbations if rollouts else ():
        from bench.robust.closed_loop import has_rollouts, rollouts_under

        if has_rollouts(out.rollouts.get(applied.label), applied, rollouts):
            continue
        scorer = scorer or _Scorer(cell, ws, record, stored_projector(cell, ws, record), windows)
        done = rollouts_under(applied, cell, ws, scorer, record, rollouts, scenes=scenes)
        # written after each perturbation: a kill keeps the ones finished before it
        out = stamped(replace(out, rollouts={**out.rollouts, applied.label: done}))
        write_robust(root, out)
        measured = True
    return out, measured


class _Scorer:
    """The cell's policy and graft, rebuilt from its stored projector, scoring perturbed windows
    exactly as the cell scored its clean ones (same sampler, noise per window, features)."""

    def __init__(self, cell: CellSpec, ws, record: Record, state: dict | None, windows: Tensor):
        p = ws.profile.protocol
        self.cell, self.ws, self.windows, self.noise_seed = cell, ws, windows, p.eval_noise_seed
        self.batch = EVAL_BATCH_FACTOR * p.eval_batch_size
        self.suite = ws.suite(cell.suite)
        self.backbone = ws.backbone(cell.backbone, cell.suite, cell.release)
        device = next(self.backbone.policy.parameters()).device
        self.inputs = cell_inputs(cell, p, self.suite, ws.split(cell.suite), self.backbone,
                                  device)
        self.loop = record.measured.features_mode == "loop"
        self.feed = None
        if state is not None:
            projector = Projector(int(state["linear.weight"].shape[1]),
                                  self.backbone.info.lm_width).to(device)
            projector.load_state_dict(state)
            projector.eval()
            tower = self.backbone.native_tower_grid if cell.spec.tower else None
            self.feed = GraftFeed(projector, self.backbone.camera_keys, self.inputs.grid,
                                  tower=tower)
        if cell.encoder is not None:
            self.inputs.encoder = ws.encoder(cell.encoder)

    def entries(self, perturbations: list[Applied]) -> list[RobustEntry]:
        """One entry per perturbation, scored in ONE pass: the windows repeated once per
        perturbation (row p * W + i: window i under perturbations[p]), so the sampler runs full
        batches (EVAL_BATCH_FACTOR x the protocol's eval batch), not one short batch per
        perturbation (the sampler was 93% of a case: docs/PERFORMANCE.md). A window's bits do
        not depend on its batch (checked at severity 0); its noise is its own (common random
        numbers across perturbations)."""
        t0 = time.perf_counter()
        n = len(self.windows)
        say(self.ws.progress, f"robustness {self.cell.id}: rescoring {n} held-out windows under "
                              f"{len(perturbations)} perturbation(s)")
        bar, done = Progress(f"robustness {self.cell.id}", n * len(perturbations),
                             self.ws.progress), [0]

        def counted(pos: Tensor) -> Tensor:  # each batch of the pass asks once for its inputs
            done[0] += len(pos)
            bar.update(done[0], "windows")
            return pos

        features_for = images_for = None
        if self.cell.encoder is not None:
            per = [self._features_for(a) for a in perturbations]
            features_for = lambda pos, frames: _by_perturbation(  # noqa: E731
                counted(pos), n, lambda p, rows, sel: per[p](rows, frames[sel]))
        else:
            images_for = lambda pos, frames, imgs: _by_perturbation(  # noqa: E731
                counted(pos), n, lambda p, rows, sel: perturbations[p].images(
                    {k: v[sel] for k, v in imgs.items()}, frames[sel]))
        scores = score(self.backbone, self.suite, self.windows.repeat(len(perturbations)),
                       self.batch, self.noise_seed, feed=self.feed, features_for=features_for,
                       images_for=images_for)
        each = round((time.perf_counter() - t0) / len(perturbations), 3)  # the pass, shared
        out = []
        for p, applied in enumerate(perturbations):
            per_window = {k: v[p * n:(p + 1) * n] for k, v in scores.per_window.items()}
            # the mean as score() takes it: over the float32 per-window errors
            mse = {k: float(torch.tensor(v, dtype=torch.float32).mean())
                   for k, v in per_window.items()}
            out.append(RobustEntry(applied.to_json(), mse, per_window, eval_s=each))
        return out

    def _features_for(self, applied: Applied):
        """features_for(positions, frames) of bench.loops.evaluate.score under `applied`."""
        encoder, grid = self.inputs.encoder, self.inputs.grid
        if self.loop:  # the cell ran its encoder in the loop: so does its rescoring
            return lambda pos, frames: encode_pooled(
                encoder, applied.images(self.suite.images(frames), frames), grid)
        if applied.severity == 0:  # the identity: the very features the cell read
            views = self.ws.features(self.cell.encoder, self.cell.suite, grid)
            return lambda pos, frames: {k: v[frames] for k, v in views.items()}
        source = PerturbedWindows(self.suite, self.windows, applied)
        views = self.ws.feature_store().pooled_features(encoder, source, grid)
        return lambda pos, frames: {k: v[pos] for k, v in views.items()}


def _by_perturbation(positions: Tensor, n: int, part) -> dict[str, Tensor]:
    """{camera: rows} of a batch of repeated windows (row p * n + i), `part(p, i's, selector)`
    called once per perturbation p in the batch, concatenated in row order."""
    which = positions // n
    parts = []
    for p in torch.unique_consecutive(which).tolist():
        sel = which == p
        parts.append(part(p, positions[sel] % n, sel))
    return {k: torch.cat([x[k] for x in parts]) for k in parts[0]}
