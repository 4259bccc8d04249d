"""REPORT.md sections about where the numbers come from: per-task breakdown and provenance."""

from __future__ import annotations

import dataclasses
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
NOT_RECORDED_RUNTIME = "not recorded"  # a record or screen from before feature_runtime


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


def changed_by_run(records: list) -> set[str]:
    """Protocol fields whose recorded value differs from the profile's own (--steps, a grid
    file's values): what this run changed, which the trimmed table keeps."""
    from bench.grid.protocol import PROFILES

    changed = set()
    for r in records:
        base = PROFILES.get(r.measured.profile)
        if base is None:
            continue
        own = json.loads(json.dumps(base.protocol.to_dict()))  # as stored: tuples are lists
        changed |= {k for k, v in (r.measured.protocol or {}).items() if own.get(k, v) != v}
    return changed


def study_constants_section(records: list[dict], summary_name: str | None = None) -> str:
    """The study-vs-ours table per protocol hash, trimmed to the rows that differ from the study
    (or are not recorded) and the fields this run changed; every row is in the JSON summary
    (`protocol_constants`), linked here."""
    if not records:
        return STUDY_TABLE_INTRO + "\n\n_No records: nothing to compare._"
    parts = [STUDY_TABLE_INTRO]
    changed = changed_by_run(records)
    for h, rows in compare_records(records).items():
        shown = [r for r in rows if r.status in (DISAGREES, NOT_RECORDED) or r.field in changed]
        rest = len(rows) - len(shown)
        where = (f"[{summary_name}]({summary_name}), key `protocol_constants`" if summary_name
                 else "the JSON summary beside this report, key `protocol_constants`")
        intro = (f"Protocol `{h}`: the {len(shown)} constant(s) that differ from the study, are "
                 f"not recorded, or that this run changed from its profile; the other {rest} "
                 f"(equal to the study's, or ours where the study is silent): {where}.")
        parts.append(intro if not shown else intro + "\n\n" + table(
            [[r.constant, r.study, r.ours, f"**{r.status}**" if r.status == DISAGREES
              else r.status, r.field or "(none)", r.note] for r in shown],
            ["constant", "study", "ours", "status", "Protocol field", "note"]))
        differ = [f"{r.constant} (study {r.study}, ours {r.ours})" for r in rows
                  if r.status == DISAGREES]
        parts.append(f"Disagreements with the study under `{h}`: "
                     + ("; ".join(differ) if differ else "none") + ".")
    return "\n\n".join(parts)


def protocol_constants(records: list) -> dict:
    """Every row of the study-vs-ours table, by protocol hash: the JSON summary's copy."""
    return {h: [dataclasses.asdict(r) for r in rows]
            for h, rows in compare_records(records).items()}


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
    runtimes = extraction_runtimes(records, res.screens)
    if runtimes:  # stores from before the field: no line, the report as it was
        lines.append(runtimes)
    grid_files = Counter((g["path"], g["sha256"]) for r in records if (g := r.measured.grid_file))
    if grid_files:  # runs without --grid: no line, the report as it was
        lines.append("Grid file(s): " + ", ".join(f"`{path}` sha256 `{sha}` ({n} cells)"
                                                  for (path, sha), n in sorted(grid_files.items())))
    parts.append(bullets(lines))
    for h, recs in hashes.items():
        parts.append(f"Protocol `{h}`:\n\n```json\n"
                     f"{json.dumps(recs[0].measured.protocol or {}, indent=1, sort_keys=True)}\n```")
    parts.append(study_constants_section(records, f"{ctx.out_path.stem}_summary.json"))
    parts += _timing_tables(records)
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


def extraction_runtimes(records, screens) -> str | None:
    """One line: per encoder, the runtime(s) that extracted the stored features its cells
    (features_mode "cache") and screens read, "not recorded" for records from before the field;
    None when no record names one."""
    seen: dict[str, set[str]] = defaultdict(set)
    for r in records:
        if r.encoder is not None and r.measured.features_mode == "cache":
            seen[r.encoder].add(r.measured.feature_runtime or NOT_RECORDED_RUNTIME)
    for s in screens:
        seen[s.scores.encoder].add(s.extraction_runtime or NOT_RECORDED_RUNTIME)
    if not any(v - {NOT_RECORDED_RUNTIME} for v in seen.values()):
        return None
    return ("Feature extraction runtime per encoder (bench.resources.extraction): "
            + "; ".join(f"{e}: {', '.join(sorted(v))}" for e, v in sorted(seen.items())))


def _timing_tables(records) -> list[str]:
    """Wall time per phase summed over the cells, then per cell (with peak memory)."""
    totals = {p: sum(float(r.run.timings_s.get(p, 0.0)) for r in records) for p in PHASES}
    rows = []
    for r in sorted(records, key=lambda r: r.cell_id):
        t = r.run.timings_s
        rows.append([r.cell_id] + [num(t.get(p), 3) for p in PHASES]
                    + [num(r.run.peak_memory_mb, 4), r.training.trainable_params,
                       r.run.created or ""])
    return ["Wall time per phase, summed over finished cells (seconds):\n\n"
            + table([[num(totals[p], 4) for p in PHASES]], list(PHASES)),
            "Per cell (seconds; peak memory in MB):\n\n"
            + table(rows, ["cell"] + list(PHASES) + ["peak MB", "trainable params", "created"])]
