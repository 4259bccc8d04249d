"""Fabricated records for tests, built through the record's own constructors
(bench.results.record), so a fake can never lack what a real record has."""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from bench.grid.kinds import GRAFT, NATIVE, NATIVE_WRAPPED, get_kind
from bench.grid.protocol import TINY
from bench.results.record import (
    Failure, Identity, MeasuredUnder, Record, RunInfo, Scores, Training, cell_id,
)
from bench.results.store import ResultStore


def _default_reference(kind: str, backbone: str, suite: str, encoder: str | None,
                       seed: int, variant: str | None = None) -> str | None:
    ref = get_kind(kind).reference_cell(encoder, variant)
    if ref is None:
        return None
    ref_kind, ref_variant = ref
    return cell_id(ref_kind, backbone, suite, encoder if ref_kind != NATIVE else None, seed,
                   ref_variant)


def _scores(values: np.ndarray, n_tasks: int, chunk: int, raw_scale: float) -> Scores:
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
    return Scores(mse={"normalized": float(values.mean()), "raw": float(raw.mean())},
                  per_window={"normalized": values.tolist(), "raw": raw.tolist()},
                  window_ids=[10 * i for i in range(n_windows)], n_windows=n_windows,
                  window_task=window_task, tasks=tasks, per_task=per_task,
                  per_horizon={"normalized": (values.mean() * ramp).tolist(),
                               "raw": (raw.mean() * ramp).tolist()})


def make_record(*, kind: str = GRAFT, backbone: str = "smolvla", suite: str = "spatial",
                encoder: str | None = "dinov2_s", seed: int = 0, variant: str | None = None,
                level: float = 0.1, noise: float = 0.0, per_window: list[float] | None = None,
                n_windows: int = 24, n_tasks: int = 2, chunk: int = 5, raw_scale: float = 2.0,
                **overrides) -> Record:
    """A record whose normalised per-window MSE averages exactly `level`.

    Window difficulty is a fixed ramp shared by all cells (0.5x .. 1.5x `level`), so paired
    differences between cells built with noise=0 are proportional to that ramp. `noise` adds
    per-window jitter seeded by the cell id and centred, so the cell mean stays `level`.
    `per_window` replaces all of this. Raw values are `raw_scale` x normalised. `overrides`:
    any record field by its JSON name (Record.replace).
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
    record = Record(
        Identity(this_id, kind, backbone, suite, encoder, seed, variant,
                 _default_reference(kind, backbone, suite, encoder, seed, variant)),
        MeasuredUnder(profile="tiny", protocol=TINY.protocol.to_dict(),
                      protocol_hash=TINY.protocol.hash),
        _scores(values, n_tasks, chunk, raw_scale),
        Training(trainable_params=1000, projector_params=1000,
                 loss_curve=[[0, 1.0], [10, 0.5]]),
        RunInfo(timings_s={"build": 0.5, "features": 1.0, "train": 2.0, "eval": 0.5,
                           "total": 4.0},
                peak_memory_mb=100.0, device="cpu", hardware="test cpu",
                versions={"torch": "2.11.0", "lerobot": "0.6.1", "timm": "1.0.31",
                          "python": "3.12"},
                git_commit="0000000", created="2026-01-01T00:00:00+00:00"),
    )
    if "window_ids" in overrides and "n_windows" not in overrides:
        overrides["n_windows"] = len(overrides["window_ids"])
    return record.replace(**overrides) if overrides else record


def make_failed(*, kind: str = GRAFT, backbone: str = "smolvla", suite: str = "spatial",
                encoder: str | None = "dinov2_s", seed: int = 0, variant: str | None = None,
                error: str = "RuntimeError: boom") -> Failure:
    """A failed-cell record as the runner writes it to failed/."""
    return Failure(Identity(cell_id(kind, backbone, suite, encoder, seed, variant), kind,
                            backbone, suite, encoder, seed, variant),
                   error, TINY.protocol.hash)


def make_grid(levels: dict[tuple[str, str, str], float], seeds: tuple[int, ...] = (0, 1), *,
              native: dict[tuple[str, str], tuple[float, float]] | None = None,
              seed_jitter: float = 0.0, **record_kwargs) -> list[Record]:
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


def save_record(results_dir: str | Path, record: Record | Failure) -> Path:
    """Write one record (cells/) or failure (failed/) through the store."""
    store = ResultStore(results_dir)
    return store.write_failure(record) if isinstance(record, Failure) else store.write(record)


def make_calibration_study(results_dir: str | Path, levels: dict[str, float],
                           seeds: tuple[int, ...] = (0, 1), backbone: str = "smolvla",
                           suite: str = "spatial") -> ResultStore:
    """A `--screen --screen-keep all` results dir, fabricated: per encoder a graft record at
    `levels[encoder]` per seed (noise 0.001) and a screen whose every supervised proxy's gain is
    -level (a perfect screen: tau-b 1), entropy 0.9 (all tie)."""
    from bench.screen.records import ScreenConditions, ScreenScores, new_screen_record

    store = ResultStore(results_dir)
    for encoder, level in levels.items():
        for seed in seeds:
            store.write(make_record(backbone=backbone, suite=suite, encoder=encoder, seed=seed,
                                    level=level, noise=0.001))
        screen = ScreenScores(encoder, backbone, suite, seconds=0.5, entropy=0.9)
        screen.proxies = {p: {"state": 0.1, "state+features": 0.1 - level, "gain": -level}
                          for p in ("logme", "ridge", "knn")}
        store.write_screen(new_screen_record(screen, ScreenConditions("h", "f", "fp16"), 2.0))
    return store
