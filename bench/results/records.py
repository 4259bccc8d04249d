"""Result records on disk: load and validate a results dir; fabricate records for tests.

Layout of a results dir (one JSON file per cell; nothing here reads in-memory run state):

    RESULTS_DIR/cells/<cell_id>.json    finished cells  (status "ok", schema 1)
    RESULTS_DIR/failed/<cell_id>.json   failed cells    (status "failed", with "error")
    RESULTS_DIR/grid.json               optional: {"expected": [cell_id, ...], "profile": "tiny"}
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.grid.kinds import GRAFT, NATIVE, NATIVE_WRAPPED, get_kind
from bench.results.record import SCHEMA_VERSION, cell_id, validate_record

@dataclass
class Results:
    """Everything a results dir holds, validated. `skipped` lists (path, reason) of bad files."""

    root: Path
    records: list[dict] = field(default_factory=list)
    failed: list[dict] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    expected: list[str] | None = None
    grid_profile: str | None = None

    @property
    def missing(self) -> list[str]:
        """Cell ids in grid.json that have neither a record nor a failure file."""
        if self.expected is None:
            return []
        seen = {r["cell_id"] for r in self.records} | {f["cell_id"] for f in self.failed}
        return [cid for cid in self.expected if cid not in seen]


def _read_json(path: Path) -> dict:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def load_results(results_dir: str | Path) -> Results:
    """Read cells/, failed/ and grid.json under `results_dir`; bad files go to `skipped`."""
    root = Path(results_dir)
    results = Results(root=root)
    seen: set[str] = set()
    for path in sorted((root / "cells").glob("*.json")):
        try:
            record = _read_json(path)
            validate_record(record)
        except (OSError, ValueError, TypeError, AttributeError) as err:
            results.skipped.append((str(path.relative_to(root)), f"{type(err).__name__}: {err}"))
            continue
        if record["cell_id"] in seen:
            results.skipped.append((str(path.relative_to(root)),
                                    f"duplicate cell_id {record['cell_id']!r}"))
            continue
        seen.add(record["cell_id"])
        results.records.append(record)
    for path in sorted((root / "failed").glob("*.json")):
        try:
            failure = _read_json(path)
            if not isinstance(failure, dict) or "cell_id" not in failure:
                raise ValueError("no cell_id")
        except (OSError, ValueError) as err:
            results.skipped.append((str(path.relative_to(root)), f"{type(err).__name__}: {err}"))
            continue
        if failure["cell_id"] not in seen:  # a later successful rerun supersedes a failure
            results.failed.append(failure)
    grid_path = root / "grid.json"
    if grid_path.exists():
        try:
            grid = _read_json(grid_path)
            results.expected = [str(c) for c in grid["expected"]]
            results.grid_profile = grid.get("profile")
        except (OSError, ValueError, KeyError, TypeError) as err:
            results.skipped.append(("grid.json", f"{type(err).__name__}: {err}"))
    return results


def save_record(results_dir: str | Path, record: dict) -> Path:
    """Write one record to cells/ (status ok) or failed/ (status failed); returns the path."""
    sub = "failed" if record.get("status") == "failed" else "cells"
    path = Path(results_dir) / sub / f"{record['cell_id']}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1), encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------------------
# Fabricated records (tests, demos). Real records are written by the cell runner.


def _default_reference(kind: str, backbone: str, suite: str, encoder: str | None,
                       seed: int) -> str | None:
    ref = get_kind(kind).reference(encoder)
    if ref is None:
        return None
    return cell_id(ref, backbone, suite, encoder if ref == GRAFT else None, seed)


def make_record(*, kind: str = GRAFT, backbone: str = "smolvla", suite: str = "spatial",
                encoder: str | None = "dinov2_s", seed: int = 0, variant: str | None = None,
                level: float = 0.1, noise: float = 0.0, per_window: list[float] | None = None,
                n_windows: int = 24, n_tasks: int = 2, chunk: int = 5, raw_scale: float = 2.0,
                **overrides) -> dict:
    """A schema-1 record whose normalised per-window MSE averages exactly `level`.

    Window difficulty is a fixed ramp shared by all cells (0.5x .. 1.5x `level`), so paired
    differences between cells built with noise=0 are proportional to that ramp. `noise` adds
    per-window jitter seeded by the cell id and centred, so the cell mean stays `level`.
    `per_window` replaces all of this. Raw values are `raw_scale` x normalised.
    """
    if get_kind(kind).encoder == "none":
        encoder = None
    get_kind(kind).check(encoder, variant)  # only cells the runner could write
    this_id = cell_id(kind, backbone, suite, encoder, seed, variant)
    if per_window is None:
        difficulty = np.linspace(0.5, 1.5, n_windows)
        rng = np.random.default_rng(zlib.crc32(this_id.encode()))
        jitter = rng.standard_normal(n_windows)
        values = level * difficulty + noise * (jitter - jitter.mean())
    else:
        values = np.asarray(per_window, dtype=float)
        n_windows = len(values)
    raw = values * raw_scale
    window_task = [i % n_tasks for i in range(n_windows)]
    tasks = [f"task {t}: put the bowl {t}" for t in range(n_tasks)]
    per_task = {}
    for t, name in enumerate(tasks):
        idx = [i for i, wt in enumerate(window_task) if wt == t]
        per_task[name] = {"normalized": float(values[idx].mean()) if idx else float("nan"),
                          "raw": float(raw[idx].mean()) if idx else float("nan"), "n": len(idx)}
    ramp = np.linspace(0.6, 1.4, chunk)
    from bench.grid.protocol import TINY  # local import: records stay readable without the runner

    record = {
        "schema": SCHEMA_VERSION, "status": "ok", "cell_id": this_id, "kind": kind,
        "backbone": backbone, "suite": suite, "encoder": encoder, "seed": seed,
        "variant": variant, "reference": _default_reference(kind, backbone, suite, encoder, seed),
        "profile": "tiny", "protocol": TINY.protocol.to_dict(),
        "protocol_hash": TINY.protocol.hash,
        "mse": {"normalized": float(values.mean()), "raw": float(raw.mean())},
        "per_window": {"normalized": values.tolist(), "raw": raw.tolist()},
        "window_ids": [10 * i for i in range(n_windows)], "window_task": window_task,
        "tasks": tasks, "per_task": per_task,
        "per_horizon": {"normalized": (values.mean() * ramp).tolist(),
                        "raw": (raw.mean() * ramp).tolist()},
        "n_windows": n_windows, "trainable_params": 1000, "projector_params": 1000,
        "loss_curve": [[0, 1.0], [10, 0.5]],
        "timings_s": {"build": 0.5, "features": 1.0, "train": 2.0, "eval": 0.5, "total": 4.0},
        "peak_memory_mb": 100.0, "device": "cpu", "hardware": "test cpu",
        "versions": {"torch": "2.11.0", "lerobot": "0.6.1", "timm": "1.0.31", "python": "3.12"},
        "git_commit": "0000000", "created": "2026-01-01T00:00:00+00:00",
    }
    record.update(overrides)
    return record


def make_failed(*, kind: str = GRAFT, backbone: str = "smolvla", suite: str = "spatial",
                encoder: str | None = "dinov2_s", seed: int = 0, variant: str | None = None,
                error: str = "RuntimeError: boom") -> dict:
    """A failed-cell record as the runner writes it to failed/."""
    return {"cell_id": cell_id(kind, backbone, suite, encoder, seed, variant), "kind": kind,
            "backbone": backbone, "suite": suite, "encoder": encoder, "seed": seed,
            "variant": variant, "error": error, "status": "failed"}


def make_grid(levels: dict[tuple[str, str, str], float], seeds: tuple[int, ...] = (0, 1), *,
              native: dict[tuple[str, str], tuple[float, float]] | None = None,
              seed_jitter: float = 0.0, **record_kwargs) -> list[dict]:
    """Graft records for {(backbone, suite, encoder): level} x seeds, plus native and
    native_wrapped cells from {(backbone, suite): (native_level, wrapped_level)}.
    `seed_jitter` shifts each seed's level by +seed_jitter*seed (seed-dependent cells)."""
    records = []
    for (backbone, suite, encoder), level in levels.items():
        for seed in seeds:
            records.append(make_record(backbone=backbone, suite=suite, encoder=encoder,
                                       seed=seed, level=level + seed_jitter * seed,
                                       **record_kwargs))
    for (backbone, suite), (native_level, wrapped_level) in (native or {}).items():
        for seed in seeds:
            for kind, level in ((NATIVE, native_level), (NATIVE_WRAPPED, wrapped_level)):
                records.append(make_record(kind=kind, backbone=backbone, suite=suite, seed=seed,
                                           level=level, **record_kwargs))
    return records
