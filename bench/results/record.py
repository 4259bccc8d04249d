"""The cell record: its schema version, its cell-id format, building finished and failed records,
and validating them. The one owner of that format: the runner, the executors, the store's
readers, the baselines and the report all go through here.

A finished record (RESULTS_DIR/cells/<cell_id>.json, status "ok") holds what the cell is (kind,
backbone, suite, encoder, seed, variant, reference), what it was measured under (profile,
protocol and its hash, checkpoint and normaliser, feature mode), the scores (bench.run.evaluate:
mse, per_window, window_ids, per_task, per_horizon, ...), what trained (parameter counts, loss
curve, probe loss) and where and when (timings, memory, device, versions, commit). A failed
record (failed/<cell_id>.json) holds what the cell is, the protocol hash and the error line.
"""

from __future__ import annotations

import datetime as dt
import math

from bench.grid.kinds import get_kind

SCHEMA_VERSION = 1

REQUIRED_KEYS = (
    "cell_id", "kind", "backbone", "suite", "encoder", "seed", "mse", "per_window",
    "window_ids", "n_windows",
)


def cell_id(kind: str, backbone: str, suite: str, encoder: str | None, seed: int,
            variant: str | None = None) -> str:
    """smolvla-spatial-dinov2_s-seed0, smolvla-spatial-native-seed0,
    smolvla-spatial-pixels-pool_half-seed0, smolvla-spatial-native-zero_image_eval-seed0."""
    parts = [backbone, suite, *get_kind(kind).id_parts(encoder, variant), f"seed{seed}"]
    return "-".join(parts)


def identity(cell) -> dict:
    """What a cell is: the first fields of both record forms."""
    ref = cell.reference
    return {"cell_id": cell.id, "kind": cell.kind, "backbone": cell.backbone,
            "suite": cell.suite, "encoder": cell.encoder, "seed": cell.seed,
            "variant": cell.variant, "reference": ref.id if ref else None}


def ok_record(cell, *, measured_under: dict, scores: dict, training: dict, run: dict) -> dict:
    """A finished cell's record. `measured_under`: grid, features_mode, profile, protocol,
    protocol_hash, checkpoint; `scores`: bench.run.evaluate.score's dict; `training`: parameter
    counts, projector_from, loss_curve, probe_loss, encoder_weights; `run`: timings_s,
    peak_memory_mb, device, hardware, versions, git_commit (and rollouts when rolled out)."""
    record = {"schema": SCHEMA_VERSION, "status": "ok", **identity(cell), **measured_under,
              **scores, **training, **run,
              "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")}
    if record.get("rollouts") is None:
        record.pop("rollouts", None)
    else:  # after "created", where it always was
        record["rollouts"] = record.pop("rollouts")
    validate_record(record)
    return record


def failure_record(cell, protocol_hash: str, error: BaseException) -> dict:
    """The record a failed cell leaves in the store, whichever executor ran it."""
    out = identity(cell)
    out.pop("reference")
    return {**out, "error": f"{type(error).__name__}: {error}", "protocol_hash": protocol_hash,
            "status": "failed"}


def validate_record(record: dict) -> None:
    """Raise ValueError naming the first problem of a finished-cell record."""
    if not isinstance(record, dict):
        raise ValueError(f"record is a {type(record).__name__}, expected a JSON object")
    if record.get("schema") != SCHEMA_VERSION:
        raise ValueError(f"schema {record.get('schema')!r}, this reader knows {SCHEMA_VERSION}")
    if record.get("status") != "ok":
        raise ValueError(f"status {record.get('status')!r} in cells/, expected 'ok'")
    missing = [k for k in REQUIRED_KEYS if k not in record]
    if missing:
        raise ValueError(f"missing keys {missing}")
    get_kind(record["kind"]).check(record["encoder"], record.get("variant"))
    expected_id = cell_id(record["kind"], record["backbone"], record["suite"], record["encoder"],
                          record["seed"], record.get("variant"))
    if record["cell_id"] != expected_id:
        raise ValueError(f"cell_id {record['cell_id']!r} is not what its fields say "
                         f"({expected_id!r})")
    n = record["n_windows"]
    for metric in ("normalized", "raw"):
        values = record["per_window"].get(metric)
        if values is None or len(values) != n:
            raise ValueError(f"per_window.{metric} has {None if values is None else len(values)} "
                             f"values, n_windows is {n}")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise ValueError(f"per_window.{metric} holds non-finite values (diverged cell?)")
        mse = record["mse"].get(metric)
        if not isinstance(mse, (int, float)) or not math.isfinite(mse):
            raise ValueError(f"mse.{metric} is {mse!r}, expected a finite number")
    if len(record["window_ids"]) != n:
        raise ValueError(f"window_ids has {len(record['window_ids'])} values, n_windows is {n}")
