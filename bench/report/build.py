"""Build REPORT.md (plus a tidy per-cell CSV, a JSON summary and PNG figures) from a results dir.

    python -m bench.report RESULTS_DIR [--out REPORT.md]   (bench.report.cli checks it first)

Only stored records are read (bench.results.store). Files written beside the report at OUT:
OUT, <stem>_cells.csv, <stem>_summary.json and <stem>_plots/*.png (linked relatively).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import sys
import traceback
from pathlib import Path
from typing import Callable, Sequence

from bench.analysis.candidates import candidate_items
from bench.analysis.rankings import DEFAULT_RESAMPLES, rank_all
from bench.analysis.controls import control_deltas, vision_checks, wrapper_neutrality
from bench.analysis.family_scale import family_scale, small_model_agreements
from bench.analysis.rollouts import closed_loop_all
from bench.analysis.transfer import support_counts, transfer_all, transfer_intervals
from bench.analysis.working_group import working_groups
from bench.grid.kinds import GRAFT
from bench.results.store import Results, load_results
from bench.report.budget import TITLE as BUDGET_TITLE, budget_section, budgets
from bench.report.closed_loop import closed_loop_section
from bench.report.context import ReportContext
from bench.report.family_scale import TITLE as FAMILY_SCALE_TITLE, family_scale_section
from bench.report.lead import answer_lines
from bench.report.naive import with_naive_baselines
from bench.report.provenance import per_task_section, protocol_constants, provenance_section
from bench.report.robustness import robustness_section
from bench.report.tuning import TITLE as TUNING_TITLE, tuning_section
from bench.report.working_group import TITLE as WORKING_TITLE, working_group_section
from bench.report.screen import (SCATTER_TITLE, SECTION_TITLE, calibrations, scatter_points,
                                 screen_agreements, screen_section)
from bench.report.sections import (
    caveats, controls_section, plots_section,
    rankings_section, seed_section, tie_section, transfer_section, vision_section,
    wrapper_section,
)
from bench.results.record import NORMALIZED, RAW


SECTIONS: list[tuple[str, Callable[[ReportContext], str]]] = [
    ("Caveats", caveats),
    ("Encoder rankings", rankings_section),
    (BUDGET_TITLE, budget_section),
    ("Vision use", vision_section),
    ("Rank transfer between backbones", transfer_section),
    (FAMILY_SCALE_TITLE, family_scale_section),  # only when the grid holds ladder sizes to compare
    ("Tie bands", tie_section),
    ("Seed cells", seed_section),
    ("Wrapper neutrality", wrapper_section),
    ("Controls", controls_section),
    (TUNING_TITLE, tuning_section),  # only when the store holds tuned-encoder cells
    ("Closed loop: success beside offline MSE", closed_loop_section),
    (WORKING_TITLE, working_group_section),  # only when candidates were rolled out
    ("Per-task breakdown", per_task_section),
    (SECTION_TITLE, screen_section),  # only when the store holds screens
    ("Robustness", robustness_section),  # only when the store holds robustness records
    ("Plots", plots_section),
    ("Provenance", provenance_section),
]


def analyse(results: Results, out_path: Path, *, n_resamples: int = DEFAULT_RESAMPLES,
            random_seed: int = 0) -> ReportContext:
    """Run every analysis over the stored records once."""
    records = results.records
    rankings = rank_all(records, n_resamples=n_resamples, random_seed=random_seed)
    expected_backbones = {r.backbone for r in records} | {f.backbone
                                                             for f in results.failed}
    expected_suites = {r.suite for r in records if r.kind == GRAFT}
    candidates = candidate_items(records)
    transfers = transfer_all(rankings, backbones=[b for b in expected_backbones if b],
                             suites=sorted(expected_suites),
                             candidates=candidates) if rankings else []
    transfer_intervals(transfers, records, n_resamples=n_resamples, seed=random_seed)
    screens, filled = with_naive_baselines([r.scores for r in results.screens], records)
    verdicts = family_scale(records, candidates, n_resamples=n_resamples, seed=random_seed)
    return ReportContext(results=results, out_path=out_path, rankings=rankings,
                         transfers=transfers, support=support_counts(transfers),
                         wrapper=wrapper_neutrality(records), controls=control_deltas(records),
                         n_resamples=n_resamples,
                         closed_loop=closed_loop_all(records, n_resamples=n_resamples,
                                                     random_seed=random_seed,
                                                     candidates=candidates),
                         vision=vision_checks(records, n_resamples=n_resamples,
                                              random_seed=random_seed),
                         screen_agreements=screen_agreements(
                             screens, records, n_resamples, random_seed, candidates),
                         screen_calibrations=calibrations(results.selections, n_resamples,
                                                          random_seed),
                         screens=screens, naive_filled=filled, candidates=candidates,
                         working_groups=working_groups(records, candidates,
                                                       n_resamples=n_resamples,
                                                       random_seed=random_seed),
                         family_scale=verdicts,
                         small_model=small_model_agreements(
                             records, candidates, n_resamples=n_resamples, seed=random_seed)
                         if verdicts else [])


def _guarded(name: str, render: Callable[[ReportContext], str | None],
             ctx: ReportContext) -> str | None:
    """A section that fails renders its error instead of taking the whole report down; None:
    the section has nothing to say in this report and is left out."""
    try:
        return render(ctx)
    except Exception as err:  # noqa: BLE001 - a partial report beats none at session end
        traceback.print_exc(file=sys.stderr)
        return f"_This section could not be rendered: {type(err).__name__}: {err}_"


def render_markdown(ctx: ReportContext,
                    extra_sections: Sequence[tuple[str, str]] = ()) -> str:
    try:
        answer = answer_lines(ctx)
    except Exception as err:  # noqa: BLE001
        answer = [f"_The answer could not be computed: {type(err).__name__}: {err}_"]
    parts = ["# graftbench report", "\n\n".join(answer)]
    for title, render in SECTIONS:
        body = _guarded(title, render, ctx)
        if body is not None:
            parts += [f"## {title}", body]
    for title, body in extra_sections:
        parts.append(f"## {title}")
        parts.append(body.strip() or "_(empty)_")
    return "\n\n".join(parts).rstrip() + "\n"


CSV_COLUMNS = [
    "cell_id", "status", "kind", "backbone", "suite", "encoder", "seed", "variant", "reference",
    "profile", "protocol_hash", "mse_normalized", "mse_raw", "n_windows", "trainable_params",
    "projector_params", "time_build_s", "time_features_s", "time_train_s", "time_eval_s",
    "time_total_s", "peak_memory_mb", "device", "git_commit", "created", "error",
]


def cell_rows(results: Results) -> list[dict]:
    """Tidy rows, one per finished or failed cell (columns: CSV_COLUMNS)."""
    rows = []
    for r in sorted(results.records, key=lambda r: r.cell_id):  # finished first, then failed
        data, t = r.to_json(), r.run.timings_s
        row = {k: data[k] for k in CSV_COLUMNS if k in data}
        row.update(mse_normalized=r.mse_in(NORMALIZED), mse_raw=r.mse_in(RAW),
                   **{f"time_{p}_s": t.get(p) for p in ("build", "features", "train", "eval",
                                                        "total")})
        rows.append(row)
    for f in sorted(results.failed, key=lambda f: f.cell_id):
        data = f.to_json()
        rows.append({k: data[k] for k in CSV_COLUMNS if k in data})
    return rows


def write_csv(results: Results, path: Path) -> Path:
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for row in cell_rows(results):
            writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in CSV_COLUMNS})
    return path


def _jsonable(value):
    """Dataclasses, tuples and dict keys made JSON-safe; NaN becomes null."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _jsonable(value.to_dict() if hasattr(value, "to_dict") else
                         dataclasses.asdict(value))
    if isinstance(value, dict):
        return {str(k) if not isinstance(k, tuple) else " x ".join(map(str, k)): _jsonable(v)
                for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def summary(ctx: ReportContext) -> dict:
    """The report's numbers as one JSON-ready dict."""
    res = ctx.results
    return _jsonable({
        "answer": answer_lines(ctx),
        "profiles": sorted({r.measured.profile or "?" for r in ctx.records}),
        "protocol_hashes": sorted({r.measured.protocol_hash or "?" for r in ctx.records}),
        "rankings": ctx.rankings, "transfers": ctx.transfers, "support": ctx.support,
        "wrapper_neutrality": ctx.wrapper, "controls": ctx.controls,
        "closed_loop": ctx.closed_loop, "working_groups": ctx.working_groups,
        "vision_use": ctx.vision,
        "screen_agreement": ctx.screen_agreements,
        "family_scale": ctx.family_scale, "small_model_rung": ctx.small_model,
        "screen_calibration": ctx.screen_calibrations,
        "protocol_constants": protocol_constants(ctx.records),
        "cells": {"finished": len(ctx.records), "failed": [f.cell_id for f in res.failed],
                  "missing": res.missing, "skipped": res.skipped},
        "releases": releases_per_backbone(ctx.records),
        "variance_budget": [b.to_dict() for b in budgets(ctx)],
        "bootstrap": {"n_resamples": ctx.n_resamples,
                      "method": "paired hierarchical: releases, seeds, episodes, windows "
                                "(n - 1 of n), percentile widened by t / z",
                      "levels": {f"{r.backbone} x {r.suite}": r.interval for r in ctx.rankings}},
    })


def releases_per_backbone(records) -> dict[str, dict[int, str]]:
    """{backbone: {release index: its weights' revision}}: the releases the records name."""
    out: dict[str, dict[int, str]] = {}
    for r in records:
        out.setdefault(r.backbone, {})[int(r.release)] = str(r.measured.revision)
    return {b: dict(sorted(v.items())) for b, v in sorted(out.items())}


def _figures(ctx: ReportContext, folder: Path) -> list[tuple[str, Path]]:
    try:
        from bench.report.plots import write_plots

        from bench.report.plots import plot_proxy_scatter

        written = write_plots(ctx.rankings, ctx.transfers, ctx.records, folder,
                              closed_loop=ctx.closed_loop)
        points = scatter_points(ctx.screens, ctx.records)
        scatter = plot_proxy_scatter(points, folder / "screen_scatter.png")
        return written + ([(SCATTER_TITLE, scatter)] if scatter is not None else [])
    except Exception:  # noqa: BLE001 - the report stays useful without figures
        traceback.print_exc(file=sys.stderr)
        return []


def build_report(results_dir: str | Path, out_path: str | Path | None = None, *,
                 extra_sections: Sequence[tuple[str, str]] = (),
                 n_resamples: int = DEFAULT_RESAMPLES, random_seed: int = 0,
                 plots: bool = True) -> Path:
    """Write REPORT.md (default RESULTS_DIR/REPORT.md) with CSV, JSON and PNGs beside it.

    `extra_sections`: (title, body) markdown pairs appended after the built-in sections.
    `plots=False` skips the figures (and matplotlib) for a faster text-only report."""
    results = load_results(results_dir)
    out = Path(out_path) if out_path is not None else Path(results_dir) / "REPORT.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    ctx = analyse(results, out, n_resamples=n_resamples, random_seed=random_seed)
    if plots:
        ctx.plots = _figures(ctx, out.parent / f"{out.stem}_plots")
    out.write_text(render_markdown(ctx, extra_sections), encoding="utf-8")
    write_csv(results, out.parent / f"{out.stem}_cells.csv")
    (out.parent / f"{out.stem}_summary.json").write_text(
        json.dumps(summary(ctx), indent=1, allow_nan=False), encoding="utf-8")
    return out
