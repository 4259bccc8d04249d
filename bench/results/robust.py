"""The robustness record of a cell (the robustness tier): its stored projector rescored on
perturbed held-out windows, one entry per perturbation (bench.robust.perturbations). One JSON file
per cell, written atomically, beside the cell records:

    RESULTS_DIR/robust/<cell_id>.json

A robustness record belongs to ONE measurement of its cell: `base` names it (the cell record's
protocol hash, creation stamp and projector sha256). A record whose base is not the cell's stored
record any more (the cell was measured again) is stale: never resumed, left out of the report.
This module is the only reader and writer of these files.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from bench.results.record import SPACES, Record
from bench.results.jsonfile import atomic_write_json

ROBUST = "robust"
SCHEMA = 1


def base_of(record: Record) -> dict:
    """What identifies the measurement a robustness record rescored."""
    return {"protocol_hash": record.measured.protocol_hash, "created": record.run.created,
            "projector_sha256": record.training.projector_sha256}


@dataclass(frozen=True)
class RobustEntry:
    """One perturbation's scores: per_window[space] aligned with the record's window_ids."""

    perturbation: dict  # bench.robust.perturbations.Applied.to_json(): kind, severity, params, ...
    mse: dict[str, float]
    per_window: dict[str, list[float]]
    eval_s: float = 0.0

    @property
    def kind(self) -> str:
        return self.perturbation["kind"]

    @property
    def severity(self) -> int:
        return int(self.perturbation["severity"])

    @property
    def label(self) -> str:
        """"kind:severity", as the record's `rollouts` keys it (perturbations.Applied.label)."""
        return f"{self.kind}:{self.severity}"


@dataclass(frozen=True)
class RobustRecord:
    """Every perturbation measured for one cell (kind, backbone, suite, encoder, seed: its
    identity as the cell record spells it)."""

    cell_id: str
    kind: str
    backbone: str
    suite: str
    encoder: str | None
    seed: int
    base: dict
    window_ids: list[int]
    entries: list[RobustEntry] = field(default_factory=list)
    timings_s: dict = field(default_factory=dict)
    created: str | None = None
    # Closed loop (--rollouts N too; native and the best graft): "kind:severity" -> the
    # rollouts under it (bench.robust.closed_loop.rollouts_under), paired with the cell record's
    # run.rollouts episode by episode.
    rollouts: dict[str, dict] = field(default_factory=dict)

    def entry(self, perturbation: dict) -> RobustEntry | None:
        """The stored entry measured under exactly `perturbation` (params, seed, version)."""
        return next((e for e in self.entries if e.perturbation == perturbation), None)

    def is_for(self, record: Record) -> bool:
        """Rescored from `record` (the cell's stored measurement), not an earlier one."""
        return (self.base == base_of(record)
                and set(self.window_ids) <= set(record.scores.window_ids))

    def to_json(self) -> dict:
        return {"schema": SCHEMA, **asdict(self)}

    @classmethod
    def from_json(cls, data: dict) -> RobustRecord:
        """A validated record; ValueError naming the first problem."""
        if not isinstance(data, dict) or data.get("schema") != SCHEMA:
            raise ValueError(f"not a robustness record of schema {SCHEMA}")
        data = {k: v for k, v in data.items() if k != "schema"}
        entries = [RobustEntry(**e) for e in data.pop("entries", [])]
        record = cls(**data, entries=entries)
        n = len(record.window_ids)
        for e in entries:
            for space in SPACES:
                values = e.per_window.get(space) or []
                if len(values) != n or not all(math.isfinite(v) for v in values):
                    raise ValueError(f"{record.cell_id} {e.kind}:{e.severity}: per_window."
                                     f"{space} is not {n} finite values")
        return record


def stamped(record: RobustRecord) -> RobustRecord:
    """`record` created now (UTC, seconds)."""
    from dataclasses import replace

    return replace(record, created=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"))


def robust_path(results_dir: str | Path, cell_id: str) -> Path:
    return Path(results_dir) / ROBUST / f"{cell_id}.json"


def write_robust(results_dir: str | Path, record: RobustRecord) -> Path:
    path = robust_path(results_dir, record.cell_id)
    atomic_write_json(path, record.to_json())
    return path


def load_robust(results_dir: str | Path, cell_id: str) -> RobustRecord | None:
    """The stored robustness record of `cell_id`; None when absent or unreadable."""
    path = robust_path(results_dir, cell_id)
    try:
        return RobustRecord.from_json(json.loads(path.read_text())) if path.is_file() else None
    except (OSError, ValueError, TypeError):
        return None


def load_all_robust(results_dir: str | Path) -> tuple[list[RobustRecord], list[tuple[str, str]]]:
    """Every robustness record under `results_dir`, and (file, reason) of those unreadable."""
    records, skipped = [], []
    for path in sorted((Path(results_dir) / ROBUST).glob("*.json")):
        try:
            records.append(RobustRecord.from_json(json.loads(path.read_text())))
        except (OSError, ValueError, TypeError) as e:
            skipped.append((f"{ROBUST}/{path.name}", f"{type(e).__name__}: {e}"))
    return records, skipped
