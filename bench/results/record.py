"""The cell record, typed: the ONE place a record key is spelled (as a dataclass field name).

A finished record (RESULTS_DIR/cells/<cell_id>.json, status "ok") is a `Record` of five parts:
what the cell is (`Identity`), what it was measured under (`MeasuredUnder`: profile, protocol and
its hash, checkpoint and normaliser, feature mode), its scores (`Scores`: mse, per window, per
task, per horizon step), what trained (`Training`) and where and when (`RunInfo`). A failed cell
leaves a `Failure` (failed/<cell_id>.json): what the cell is, the protocol hash and the error.

On disk a record is one flat JSON object, schema 1 (unchanged by the typing: every key is the name
of a field of one part, bench.results.parts). `Record.from_json` validates and is the only way in; `to_json` the only
way out; bench.results.store the only reader and writer of files. Whether a stored record may
stand for this run is bench.results.current.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from dataclasses import MISSING, dataclass, field, fields

from bench.grid.kinds import cell_id, get_kind  # noqa: F401  (cell_id: re-exported)
from bench.results.parts import (  # noqa: F401  (the parts are re-exported: one import for users)
    NORMALIZED, RAW, SPACES, Identity, MeasuredUnder, RunInfo, Scores, Training, checkpoint_of,
    checkpoint_revision, flat, task_score,
)

SCHEMA_VERSION = 1
OK, FAILED = "ok", "failed"
SCHEMA_KEY = _SCHEMA = "schema"  # the envelope keys (a baseline file's schema key, too)
_STATUS = "status"


_PARTS = {"identity": Identity, "measured": MeasuredUnder, "scores": Scores,
          "training": Training, "run": RunInfo}


def _part(cls, data: dict):
    return cls(**{f.name: data[f.name] for f in fields(cls) if f.name in data})


def _known_keys() -> set[str]:
    return {f.name for cls in _PARTS.values() for f in fields(cls)} | {_SCHEMA, _STATUS}


class _IdentityFields:
    """A record's or a failure's identity fields, for short (both hold `identity`)."""

    cell_id = property(lambda self: self.identity.cell_id)
    kind = property(lambda self: self.identity.kind)
    backbone = property(lambda self: self.identity.backbone)
    suite = property(lambda self: self.identity.suite)
    encoder = property(lambda self: self.identity.encoder)
    seed = property(lambda self: self.identity.seed)
    variant = property(lambda self: self.identity.variant)
    release = property(lambda self: self.identity.release)


@dataclass(frozen=True)
class Record(_IdentityFields):
    """A finished cell's record. `extra`: keys this code does not know (kept, written back)."""

    identity: Identity
    measured: MeasuredUnder
    scores: Scores
    training: Training = field(default_factory=Training)
    run: RunInfo = field(default_factory=RunInfo)
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        validate_record(self.to_json())

    reference = property(lambda self: self.identity.reference)

    def mse_in(self, space: str = NORMALIZED) -> float:
        return self.scores.mse_in(space)

    # -- JSON ---------------------------------------------------------------------------------
    def to_json(self) -> dict:
        """The flat schema-1 object stored in cells/<cell_id>.json."""
        return {_SCHEMA: SCHEMA_VERSION, _STATUS: OK,
                **{k: v for part in _PARTS for k, v in flat(getattr(self, part)).items()},
                **self.extra}

    @classmethod
    def from_json(cls, data: dict) -> Record:
        """A validated Record from a stored object; ValueError naming the first problem."""
        validate_record(data)
        known = _known_keys()
        return cls(**{name: _part(part, data) for name, part in _PARTS.items()},
                   extra={k: v for k, v in data.items() if k not in known})

    def replace(self, **changes) -> Record:
        """A copy with fields changed by their JSON name (whichever part holds them)."""
        parts = {}
        for name, part_cls in _PARTS.items():
            mine = {k: changes.pop(k) for k in [f.name for f in fields(part_cls)] if k in changes}
            parts[name] = dataclasses.replace(getattr(self, name), **mine)
        return dataclasses.replace(self, **parts, extra={**self.extra, **changes})


# What a baseline file (bench.regression.baseline) keeps of a record: what it is, what it was
# measured under and the scores a later run is compared on.
# The windows' episodes and tasks: the paired interval draws episodes (files without them: windows).
_SNAPSHOT_KEYS = ("cell_id", "kind", "backbone", "suite", "encoder", "seed", "variant",
                  "protocol_hash", "checkpoint", "versions", "mse", "per_window", "window_ids",
                  "window_episode", "window_task")


def snapshot_json(record: Record) -> dict:
    """A baseline file's cell: the record's _SNAPSHOT_KEYS."""
    data = record.to_json()
    return {k: data.get(k) for k in _SNAPSHOT_KEYS}


def from_snapshot(data: dict) -> Record:
    """A baseline file's cell as a Record (what it does not keep left at defaults);
    ValueError when it is not one."""
    try:
        window_ids = data["window_ids"]
        full = {**data, _SCHEMA: SCHEMA_VERSION, _STATUS: OK, "n_windows": len(window_ids)}
        return Record.from_json({k: v for k, v in full.items() if v is not None or k in
                                 ("encoder", "variant")})
    except (KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"{type(e).__name__}: {e}") from None


def new_record(cell, *, measured: MeasuredUnder, scores: Scores, training: Training,
               run: RunInfo) -> Record:
    """A finished cell's record, stamped now (UTC, seconds)."""
    created = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    return Record(Identity.of(cell), measured, scores, training,
                  dataclasses.replace(run, created=created))


@dataclass(frozen=True)
class Failure(_IdentityFields):
    """What a failed cell leaves in failed/<cell_id>.json: never used to skip work."""

    identity: Identity
    error: str
    protocol_hash: str | None = None

    @classmethod
    def of(cls, cell, protocol_hash: str, error: BaseException) -> Failure:
        """The record a failed cell leaves in the store, whichever executor ran it."""
        return cls(Identity.of(cell), f"{type(error).__name__}: {error}", protocol_hash)

    def to_json(self) -> dict:
        out = flat(self.identity)
        out.pop("reference")
        return {**out, "error": self.error, "protocol_hash": self.protocol_hash, _STATUS: FAILED}

    @classmethod
    def from_json(cls, data: dict) -> Failure:
        if not isinstance(data, dict) or not isinstance(data.get("cell_id"), str):
            raise ValueError("no cell_id string")  # {"cell_id": 5} is no failed cell
        ident = {f.name: data.get(f.name) for f in fields(Identity)}
        return cls(Identity(**ident), str(data.get("error")), data.get("protocol_hash"))


def validate_record(record: dict) -> None:
    """Raise ValueError naming the first problem of a finished-cell record (its JSON)."""
    if isinstance(record, Record):  # bench/test_grid.py checks resumed records as new ones
        record = record.to_json()
    if not isinstance(record, dict):
        raise ValueError(f"record is a {type(record).__name__}, expected a JSON object")
    if record.get(_SCHEMA) != SCHEMA_VERSION:
        raise ValueError(f"schema {record.get(_SCHEMA)!r}, this reader knows {SCHEMA_VERSION}")
    if record.get(_STATUS) != OK:
        raise ValueError(f"status {record.get(_STATUS)!r} in cells/, expected 'ok'")
    required = [f.name for part in (Identity, Scores) for f in fields(part)
                if f.default is MISSING and f.default_factory is MISSING]  # no default: required
    missing = [k for k in required if k not in record]
    if missing:
        raise ValueError(f"missing keys {missing}")
    ident = _part(Identity, record)
    get_kind(ident.kind).check(ident.encoder, ident.variant)
    if isinstance(ident.release, bool) or not isinstance(ident.release, int) or ident.release < 0:
        raise ValueError(f"release {ident.release!r} is not a release index (an integer >= 0)")
    expected_id = cell_id(ident.kind, ident.backbone, ident.suite, ident.encoder, ident.seed,
                          ident.variant, ident.release)
    if ident.cell_id != expected_id:
        raise ValueError(f"cell_id {ident.cell_id!r} is not what its fields say "
                         f"({expected_id!r})")
    _validate_scores(_part(Scores, record))


def _validate_scores(scores: Scores) -> None:
    n = scores.n_windows
    for space in SPACES:
        values = scores.per_window.get(space)
        if values is None or len(values) != n:
            raise ValueError(f"per_window.{space} has {None if values is None else len(values)} "
                             f"values, n_windows is {n}")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise ValueError(f"per_window.{space} holds non-finite values (diverged cell?)")
        mse = scores.mse.get(space)
        if not isinstance(mse, (int, float)) or not math.isfinite(mse):
            raise ValueError(f"mse.{space} is {mse!r}, expected a finite number")
    if len(scores.window_ids) != n:
        raise ValueError(f"window_ids has {len(scores.window_ids)} values, n_windows is {n}")
