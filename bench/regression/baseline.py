"""CI regression mode, the pure part: baseline files, `--compare-fail` checks, one comparison.

A baseline is one JSON file holding, per cell, what a later run is compared on: the MSE and the
per-window MSE in both action spaces, the window ids they are aligned on, the protocol hash and the
package versions. Nothing here touches pytest; `bench.regression.run` turns `BaselineError` into
`pytest.UsageError` and verdicts into failed cases.

Noise rules (also in docs/CI.md):
- paired interval: the per-window differences of two cells scored on the same windows (aligned by
  window id), their mean, and a 95% percentile bootstrap interval of that mean (the report's: the
  held-out episodes the windows come from drawn, then their windows; windows alone for cells
  without episode ids; 2,000 replicates, fixed seed 0: the verdict is deterministic; paired.py).
- `mse:10%:paired` fails only when the threshold is exceeded AND the paired interval of
  (now - baseline) lies wholly above 0.
- `rank`: within one backbone x suite x seed (graft cells), encoders a and b are tied when the paired
  interval of (a - b) contains 0. A flip is a pair ordered one way in the baseline and the other way
  now with the pair separated (interval excluding 0) in BOTH runs; anything else is within the band.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, fields
from itertools import combinations
from pathlib import Path
from typing import Sequence

from bench.grid.kinds import GRAFT
from bench.results.current import RunConditions, differences
from bench.regression.paired import CONFIDENCE, aligned, paired_interval, separated
from bench.results.record import (
    NORMALIZED, RAW, SCHEMA_KEY, Record, from_snapshot, snapshot_json,
)

# The baseline FILE's format (a snapshot of records), not the record's (bench.results.record).
BASELINE_SCHEMA = 1
METRIC_SPACES = dict(mse=NORMALIZED, raw_mse=RAW)  # the spec's metric names -> action space
VALID_FORMS = "mse:10%, raw_mse:10%, mse:0.002 (absolute), mse:10%:paired, rank"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_SPEC = re.compile(r"^(?P<metric>mse|raw_mse):(?:(?P<pct>\d+(?:\.\d+)?)%|"
                   r"(?P<abs>\d*\.?\d+(?:[eE][-+]?\d+)?))(?P<paired>:paired)?$")


class BaselineError(ValueError):
    """A bad baseline name, file or `--compare-fail` spec (one line, names the culprit)."""


# ---------------------------------------------------------------------------------------------
# Checks: `--compare-fail` specs


@dataclass(frozen=True)
class ThresholdCheck:
    """`mse:10%` / `raw_mse:0.002` / `mse:10%:paired`: one cell, now against its baseline."""

    spec: str
    metric: str  # "mse" or "raw_mse"
    limit: float  # fraction (relative) or MSE units (absolute)
    relative: bool
    paired: bool = False
    scope = "cell"

    @property
    def space(self) -> str:
        return METRIC_SPACES[self.metric]

    def exceeded(self, base_mse: float, now_mse: float) -> bool:
        if self.relative:
            return now_mse > base_mse * (1.0 + self.limit)
        return now_mse - base_mse > self.limit

    def fails(self, base: Record, now: Record) -> str | None:
        """A one-line message when `now` regressed against `base`, else None."""
        b, n = base.mse_in(self.space), now.mse_in(self.space)
        if not self.exceeded(b, n):
            return None
        note = ""
        if self.paired:
            _, lo, hi = paired_interval(*aligned(now, base, self.space))
            if not math.isnan(lo) and lo <= 0.0:
                return None  # threshold exceeded, but within the windows' noise
            note = (" (paired windows unavailable)" if math.isnan(lo)
                    else f" (paired 95% CI of now - baseline [{lo:+.4g}, {hi:+.4g}])")
        return (f"{now.cell_id}: {self.metric} {n:.4g} vs baseline {b:.4g} "
                f"({_change(b, n)}) exceeds {self.spec}{note}")


@dataclass(frozen=True)
class RankCheck:
    """`rank`: the encoder order of one backbone x suite x seed, beyond its tie band."""

    spec: str = "rank"
    space: str = NORMALIZED
    scope = "group"

    def flips(self, base_cells: dict[str, Record], now_cells: dict[str, Record]) -> list[str]:
        """Descriptions of the flipped pairs; `*_cells` map encoder -> record of one group."""
        out = []
        for a, b in combinations(sorted(set(base_cells) & set(now_cells)), 2):
            bd, blo, bhi = paired_interval(*aligned(base_cells[a], base_cells[b], self.space))
            nd, nlo, nhi = paired_interval(*aligned(now_cells[a], now_cells[b], self.space))
            if separated(blo, bhi) and separated(nlo, nhi) and (bd > 0) != (nd > 0):
                better, worse = (a, b) if bd < 0 else (b, a)
                out.append(f"baseline {better} < {worse} by {_gap(bd, blo, bhi)}, "
                           f"now {worse} < {better} by {_gap(nd, nlo, nhi)}")
        return out

    def fails(self, base_cells: dict[str, Record], now_cells: dict[str, Record]) -> str | None:
        flips = self.flips(base_cells, now_cells)
        return f"rank flip: {'; '.join(flips)} (exceeds rank)" if flips else None


def parse_compare_fail(spec: str) -> ThresholdCheck | RankCheck:
    """`mse:10%`, `raw_mse:10%`, `mse:0.002`, `mse:10%:paired`, `rank` -> a check object."""
    text = spec.strip()
    if text == "rank":
        return RankCheck()
    m = _SPEC.match(text)
    if not m:
        raise BaselineError(f"--compare-fail {spec!r} not understood; valid forms: {VALID_FORMS}")
    relative = m["pct"] is not None
    limit = float(m["pct"]) / 100.0 if relative else float(m["abs"])
    return ThresholdCheck(text, m["metric"], limit, relative, paired=bool(m["paired"]))


def _gap(diff: float, lo: float, hi: float) -> str:
    """|diff| with its interval as magnitudes: 0.003 [0.002, 0.004]."""
    low, high = sorted((abs(lo), abs(hi)))
    return f"{abs(diff):.4g} [{low:.4g}, {high:.4g}]"


def _change(base: float, now: float) -> str:
    return f"{(now / base - 1.0) * 100:+.1f}%" if base else f"{now - base:+.4g}"


# ---------------------------------------------------------------------------------------------
# Baseline files


@dataclass(frozen=True)
class Baseline:
    """A baseline file: a named snapshot of records (what a later run is compared on)."""

    name: str
    created: str
    git_commit: str
    protocol_hash: str | None  # the one protocol of its cells, or None when several
    protocol_hashes: list[str]
    protocol: dict | None
    profile: str | None
    versions: dict
    hardware: list[str]
    machine: dict
    cells: dict[str, Record]  # cell id -> its record as snapshot (bench.results.record)
    schema: int = BASELINE_SCHEMA

    def to_json(self) -> dict:
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out[_CELLS] = {cid: snapshot_json(r) for cid, r in self.cells.items()}
        return out


_CELLS = "cells"


def baseline_path(baseline_dir: Path, name: str) -> Path:
    """NAME -> baseline_dir/NAME.json; a NAME holding '/' or ending in .json is a path itself."""
    if "/" in name or name.endswith(".json"):
        return Path(name)
    if not _NAME.match(name):
        raise BaselineError(f"baseline name {name!r}: use letters, digits, '.', '_' or '-' "
                            "(or give a path ending in .json)")
    return Path(baseline_dir) / f"{name}.json"


def snapshot(records: Sequence[Record], name: str, *, created: str, git_commit: str,
             machine: dict) -> Baseline:
    """The baseline of `records` (finished cell records)."""
    hashes = sorted({r.measured.protocol_hash for r in records})
    first = records[0] if records else None
    return Baseline(
        name=name, created=created, git_commit=git_commit,
        protocol_hash=hashes[0] if len(hashes) == 1 else None, protocol_hashes=hashes,
        protocol=first.measured.protocol if len(hashes) == 1 and first else None,
        profile=first.measured.profile if first else None,
        versions=first.run.versions if first else {},
        hardware=sorted({str(r.run.hardware) for r in records}), machine=machine,
        cells={r.cell_id: from_snapshot(snapshot_json(r)) for r in records})


def load_baseline(path: Path) -> Baseline:
    """Read and check a baseline file; BaselineError (one line, naming the file) when unusable."""
    path = Path(path)
    hint = "save one with --save-baseline NAME"
    if not path.is_file():
        raise BaselineError(f"baseline file {path} not found; {hint}")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BaselineError(f"baseline file {path} is unreadable ({str(e).splitlines()[0]}); "
                            f"{hint}") from None
    cells = data.get(_CELLS) if isinstance(data, dict) else None
    if not isinstance(cells, dict) or data.get(SCHEMA_KEY) != BASELINE_SCHEMA:
        raise BaselineError(f"baseline file {path} is not a schema-{BASELINE_SCHEMA} graftbench baseline; "
                            f"{hint}")
    records = {}
    for cid, cell in cells.items():
        try:
            records[cid] = from_snapshot(cell)
        except ValueError:
            raise BaselineError(f"baseline file {path}: cell {cid!r} lacks mse/per_window/"
                                f"window_ids; {hint}") from None
    known = {f.name for f in fields(Baseline)}
    return Baseline(**{**{k: None for k in known}, **{k: v for k, v in data.items() if k in known},
                       _CELLS: records})


def provenance_mismatch(base_cell: Record, baseline: Baseline | None, now: Record) -> list[str]:
    """What differs between how the baseline cell and the current record were measured: the
    freshness rule (bench.results.current) with the baseline cell's conditions."""
    base = base_cell.measured
    versions = base_cell.run.versions or (baseline.versions if baseline else None) or {}
    wanted = RunConditions(protocol_hash=base.protocol_hash,
                           normalizer_fingerprint=base.normalizer_fingerprint,  # never compare across normalisers
                           versions=versions, label="baseline")
    return differences(now, wanted)


# ---------------------------------------------------------------------------------------------
# One comparison of a run against a baseline


@dataclass
class CellRow:
    cell_id: str
    base_mse: float
    now_mse: float
    diff: float  # paired mean of now - baseline, normalised space
    lo: float
    hi: float
    failures: list[str] = field(default_factory=list)
    mismatch: list[str] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        return "REGRESSED" if self.failures else "ok"


@dataclass
class Comparison:
    name: str
    baseline: Baseline
    checks: list
    rows: list[CellRow] = field(default_factory=list)
    new: list[str] = field(default_factory=list)
    not_compared: list[str] = field(default_factory=list)  # "cell_id (reason)"
    flips: dict[str, str] = field(default_factory=dict)  # group id -> message
    groups_compared: int = 0

    @property
    def regressed(self) -> list[CellRow]:
        return [r for r in self.rows if r.failures]

    @property
    def mismatched(self) -> list[CellRow]:
        return [r for r in self.rows if r.mismatch]

    @property
    def failed(self) -> bool:
        return bool(self.regressed or self.flips)


def cell_failures(base_cell: Record, now: Record, checks: Sequence) -> list[str]:
    """Messages of the cell-scope checks that `now` fails against `base_cell`."""
    return [m for c in checks if c.scope == "cell" for m in [c.fails(base_cell, now)] if m]


def group_id(cell: Record) -> str:
    return cell.identity.group


def compare_run(name: str, baseline: Baseline, selected: Sequence[str], records: dict[str, Record],
                checks: Sequence) -> Comparison:
    """Compare the records of the `selected` cell ids (missing ones absent) with `baseline`."""
    comp = Comparison(name, baseline, list(checks))
    cells = baseline.cells
    for cid in selected:
        now = records.get(cid)
        if cid not in cells:
            comp.new.append(cid)
        elif now is None:
            comp.not_compared.append(f"{cid} (no record this run)")
        else:
            base = cells[cid]
            d, lo, hi = paired_interval(*aligned(now, base, NORMALIZED))
            comp.rows.append(CellRow(cid, base.mse_in(), now.mse_in(),
                                     d, lo, hi, cell_failures(base, now, checks),
                                     provenance_mismatch(base, baseline, now)))
    ran = set(selected)
    comp.not_compared += [f"{cid} (not run)" for cid in cells if cid not in ran]
    rank = [c for c in checks if c.scope == "group"]
    if rank:
        compared = {r.cell_id for r in comp.rows}
        base_groups: dict[str, dict] = {}
        now_groups: dict[str, dict] = {}
        for cid in compared:
            if cells[cid].kind == GRAFT:
                gid = group_id(cells[cid])
                base_groups.setdefault(gid, {})[cells[cid].encoder] = cells[cid]
                now_groups.setdefault(gid, {})[cells[cid].encoder] = records[cid]
        for gid in sorted(base_groups):
            if len(base_groups[gid]) < 2:
                continue
            comp.groups_compared += 1
            for check in rank:
                message = check.fails(base_groups[gid], now_groups[gid])
                if message:
                    comp.flips[gid] = f"{gid}: {message}"
    return comp


def markdown_section(comp: Comparison, path: Path | str) -> str:
    """The REPORT.md body of "Against baseline NAME"."""
    b = comp.baseline
    checks = ", ".join(f"`{c.spec}`" for c in comp.checks) or "none (report only)"
    out = [
        f"Baseline `{comp.name}` (`{path}`): saved {b.created} at graftbench commit "
        f"`{b.git_commit}`, protocol {', '.join(b.protocol_hashes or ['?'])}, "
        f"on {'; '.join(b.hardware or ['?'])}. Checks: {checks}.",
        "",
        "Change: mean over the shared held-out windows of (now - baseline) normalised MSE, with its "
        f"paired {CONFIDENCE:.0%} bootstrap interval (held-out episodes drawn, then windows).",
        "",
    ]
    if comp.mismatched:
        out += ["**Measured differently from the baseline** (compared anyway; "
                "`--compare-strict` makes this an error):", ""]
        out += [f"- {r.cell_id}: {', '.join(r.mismatch)}" for r in comp.mismatched] + [""]
    if comp.rows:
        out += ["| cell | baseline MSE | now MSE | change | paired 95% CI | verdict |",
                "| --- | ---: | ---: | ---: | --- | --- |"]
        for r in comp.rows:
            ci = "n/a" if math.isnan(r.lo) else f"[{r.lo:+.4g}, {r.hi:+.4g}]"
            verdict = "; ".join(r.failures) if r.failures else r.verdict
            out.append(f"| {r.cell_id} | {r.base_mse:.4g} | {r.now_mse:.4g} | "
                       f"{_change(r.base_mse, r.now_mse)} | {ci} | {verdict} |")
        out.append("")
    if any(c.scope == "group" for c in comp.checks):
        out.append(f"Rank check: {comp.groups_compared} backbone x suite x seed group(s) compared; "
                   f"tie band = paired {CONFIDENCE:.0%} interval containing 0; "
                   f"{len(comp.flips)} flip(s).")
        out += [""] + [f"- **{m}**" for m in comp.flips.values()]
        out.append("")
    out.append(f"New (not in the baseline, passed): {', '.join(comp.new) or 'none'}.")
    out.append("")
    out.append(f"Not compared: {', '.join(comp.not_compared) or 'none'}.")
    return "\n".join(out) + "\n"
