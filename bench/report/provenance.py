"""REPORT.md sections about where the numbers come from: per-task breakdown and provenance."""

from __future__ import annotations

import json
import os
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from bench.analysis.rankings import PRIMARY
from bench.grid.kinds import column_label
from bench.report.format import bullets, num, table
from bench.report.context import ReportContext
from bench.report.study import DISAGREES, NOT_RECORDED, OURS, STUDY, STUDY_SOURCE, compare_records

PHASES = ("build", "features", "train", "eval", "total")


def per_task_section(ctx: ReportContext) -> str:
    """Mean normalised MSE per task (rows) and encoder / native cell (columns), over seeds."""
    groups: dict[tuple[str, str], dict[str, dict[str, list[float]]]] = {}
    for r in ctx.records:
        column = column_label(r)
        if column is None:
            continue
        cols = groups.setdefault((r.backbone, r.suite), {})
        for task, values in (r.scores.per_task or {}).items():
            cols.setdefault(column, {}).setdefault(task, []).append(values.get(PRIMARY))
    if not groups:
        return "_No per-task results in the records._"
    parts = ["Mean normalised MSE per task over seeds (native columns are references):"]
    for (backbone, suite), cols in sorted(groups.items()):
        ranking = next((r for r in ctx.rankings if r.backbone == backbone and r.suite == suite),
                       None)
        ordered = [e.encoder for e in ranking.encoders] if ranking else []
        names = ordered + sorted(c for c in cols if c not in ordered)
        tasks = list(dict.fromkeys(t for c in names for t in cols.get(c, {})))
        rows = []
        for task in tasks:
            row = [task]
            for c in names:
                vals = [v for v in cols.get(c, {}).get(task, []) if v is not None]
                row.append(num(float(np.mean(vals))) if vals else "n/a")
            rows.append(row)
        parts.append(f"### {backbone} x {suite}")
        parts.append(table(rows, ["task"] + names))
    return "\n\n".join(parts)


def _last_line(text) -> str:
    lines = str(text or "").strip().splitlines()
    return lines[-1] if lines else ""


def _distinct(values) -> str:
    seen = sorted({json.dumps(v, sort_keys=True) if isinstance(v, dict) else str(v)
                   for v in values if v is not None})
    return ", ".join(seen) if seen else "unknown"


STUDY_TABLE_INTRO = (
    f"**Protocol constants: the study's and ours.** Study values: {STUDY_SOURCE}. Status "
    f"`{STUDY}`: ours equals the study's; `{OURS}`: a constant of ours the study does not give; "
    f"`{DISAGREES}`: ours differs from the study's; `{NOT_RECORDED}`: the records do not say "
    f"what we used."
)


def study_constants_section(records: list[dict]) -> str:
    """The study-vs-ours table per protocol hash, disagreements listed under it."""
    if not records:
        return STUDY_TABLE_INTRO + "\n\n_No records: nothing to compare._"
    parts = [STUDY_TABLE_INTRO]
    for h, rows in compare_records(records).items():
        parts.append(f"Protocol `{h}`:\n\n" + table(
            [[r.constant, r.study, r.ours, f"**{r.status}**" if r.status == DISAGREES
              else r.status, r.field or "(none)", r.note] for r in rows],
            ["constant", "study", "ours", "status", "Protocol field", "note"]))
        differ = [f"{r.constant} (study {r.study}, ours {r.ours})" for r in rows
                  if r.status == DISAGREES]
        parts.append(f"Disagreements with the study under `{h}`: "
                     + ("; ".join(differ) if differ else "none") + ".")
    return "\n\n".join(parts)


def provenance_section(ctx: ReportContext) -> str:
    res, records = ctx.results, ctx.records
    parts = []
    hashes = defaultdict(list)
    for r in records:
        hashes[r.measured.protocol_hash or "unrecorded"].append(r)
    # Relative to the report's folder: a committed report names no folder of one machine.
    results_dir = os.path.relpath(Path(res.root).resolve(), ctx.out_path.parent.resolve())
    lines = [
        f"Results dir: `{results_dir}` (relative to this report)",
        f"Profile(s): {_distinct([r.measured.profile for r in records] + [res.grid_profile])}",
        f"Protocol hash(es): {', '.join(f'`{h}` ({len(v)} cells)' for h, v in hashes.items())}"
        if hashes else "Protocol hash(es): none",
        f"Seeds: {sorted({r.seed for r in records})}",
        f"Backbones: {sorted({r.backbone for r in records})}; suites: "
        f"{sorted({r.suite for r in records})}",
        f"Git commit(s): {_distinct([r.run.git_commit for r in records])}",
        f"Versions: {_distinct([r.run.versions for r in records])}",
        f"Hardware: {_distinct([r.run.hardware for r in records])}; device(s): "
        f"{_distinct([r.run.device for r in records])}",
        f"Cells: {len(records)} finished, {len(res.failed)} failed, {len(res.missing)} missing"
        + (f" of {len(res.expected)} expected (grid.json)" if res.expected is not None
           else " (no grid.json: missing cells cannot be listed)")
        + f", {len(res.skipped)} unreadable files skipped"
        + (f", {len(res.set_aside)} unreadable record(s) moved aside to `unreadable/` and "
           "measured again" if res.set_aside else ""),
    ]
    grid_files = Counter((g["path"], g["sha256"]) for r in records if (g := r.measured.grid_file))
    if grid_files:  # runs without --grid: no line, the report as it was
        lines.append("Grid file(s): " + ", ".join(f"`{path}` sha256 `{sha}` ({n} cells)"
                                                  for (path, sha), n in sorted(grid_files.items())))
    parts.append(bullets(lines))
    for h, recs in hashes.items():
        parts.append(f"Protocol `{h}`:\n\n```json\n"
                     f"{json.dumps(recs[0].measured.protocol or {}, indent=1, sort_keys=True)}\n```")
    parts.append(study_constants_section(records))
    totals = {p: sum(float(r.run.timings_s.get(p, 0.0)) for r in records)
              for p in PHASES}
    parts.append("Wall time per phase, summed over finished cells (seconds):\n\n"
                 + table([[num(totals[p], 4) for p in PHASES]], list(PHASES)))
    rows = []
    for r in sorted(records, key=lambda r: r.cell_id):
        t = r.run.timings_s
        rows.append([r.cell_id] + [num(t.get(p), 3) for p in PHASES]
                    + [num(r.run.peak_memory_mb, 4), r.training.trainable_params,
                       r.run.created or ""])
    parts.append("Per cell (seconds; peak memory in MB):\n\n"
                 + table(rows, ["cell"] + list(PHASES) + ["peak MB", "trainable params",
                                                         "created"]))
    parts.append("Cells missing (expected in grid.json, neither finished nor failed): "
                 + (", ".join(f"`{c}`" for c in res.missing) if res.missing else
                    ("none" if res.expected is not None else "unknown (no grid.json)")))
    if res.failed:
        parts.append("Failed cells:\n\n" + table(
            [[f.cell_id, _last_line(f.error)] for f in res.failed], ["cell", "error (last line)"]))
    else:
        parts.append("Failed cells: none")
    if res.skipped:
        parts.append("Unreadable or invalid files skipped:\n\n"
                     + table([list(s) for s in res.skipped], ["file", "reason"]))
    return "\n\n".join(parts)
