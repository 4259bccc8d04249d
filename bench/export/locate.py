"""Which cell to export, and whether it can be: every bad input is one ExportError line naming
the thing and the fix."""

from __future__ import annotations

import difflib
import shlex
from pathlib import Path

from bench.grid.kinds import GRAFT
from bench.results.record import NORMALIZED, Record
from bench.results.store import load_failure, load_results


class ExportError(RuntimeError):
    """Bad input to bench.export: one line, naming the thing and the fix."""


def results_of(results_dir: str | Path):
    root = Path(results_dir)
    if not (root / "cells").is_dir():
        raise ExportError(f"no results at {root} (no cells/ folder): pass the --results-dir "
                          "of a `pytest bench` run")
    return load_results(root)


def find_record(results_dir: str | Path, cell_id: str) -> Record:
    """The finished graft record of `cell_id`, or an ExportError saying why not."""
    results = results_of(results_dir)
    by_id = {r.cell_id: r for r in results.records}
    if cell_id not in by_id:
        failure = load_failure(results_dir, cell_id)
        if failure is not None:
            raise ExportError(f"cell {cell_id} failed ({failure.error}): fix it and run it "
                              f"again ({rerun_command(results, failure)})")
        close = difflib.get_close_matches(cell_id, list(by_id), n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise ExportError(f"no cell {cell_id!r} in {results_dir} ({len(by_id)} cells){hint} "
                          "(`python -m bench.export --list --results-dir DIR` lists them)")
    record = by_id[cell_id]
    if record.kind != GRAFT:
        raise ExportError(f"cell {cell_id} is a {record.kind!r} cell: only graft cells export "
                          "(their encoder replaces the vision tower); pick a graft cell")
    return record


def rerun_command(results, failure) -> str:
    """The `pytest bench` command that measures the failed cell again as its run measured it:
    the profile, study file and steps of the records that share its protocol hash (else the
    profile grid.json names), the cell's own backbone, suite, encoder, seed and kind, -k its id.
    A bare `-k CELL` selects nothing for a cell outside the default grid (exit 5)."""
    same = [r.measured for r in results.records
            if r.measured.protocol_hash == failure.protocol_hash]
    measured = same[0] if same else None
    profile = measured.profile if measured is not None else results.grid_profile
    grid = (measured.grid_file or {}).get("path") if measured is not None else None
    args = ["pytest", "bench"] + (["--grid", grid] if grid else [])
    args += ["--profile", profile] if profile else []
    steps = (measured.protocol or {}).get("steps") if measured is not None else None
    if steps is not None and not grid and profile and _profile_steps(profile) != steps:
        args += ["--steps", str(steps)]
    ident = failure.identity
    args += ["--backbones", ident.backbone, "--suites", ident.suite, "--seeds", str(ident.seed)]
    args += ["--encoders", ident.encoder] if ident.encoder else []
    from bench.grid.kinds import control_kinds

    args += ["--controls", ident.kind if ident.kind in control_kinds() else "none"]
    return shlex.join(args + ["-k", ident.cell_id, "--results-dir", str(results.root)])


def _profile_steps(name: str) -> int | None:
    from bench.grid.protocol import PROFILES

    profile = PROFILES.get(name)
    return profile.protocol.steps if profile is not None else None


def exportable(record: Record) -> bool:
    """A graft whose encoder is a timm architecture (the plugin rebuilds it by name)."""
    return why_not_exportable(record) is None


def why_not_exportable(record: Record) -> str | None:
    """Why the LeRobot plugin cannot rebuild this graft's encoder (None: it can). The plugin
    rebuilds an encoder from timm by its architecture name alone: a user's PKG.MODULE:FACTORY
    or a known-answer encoder has no such name."""
    from encoders import get_spec, is_user_encoder

    if record.encoder is None:
        return "it has no encoder"
    if is_user_encoder(record.encoder):
        return (f"its encoder {record.encoder!r} is your own module's (PKG.MODULE:FACTORY), and "
                "the LeRobot plugin rebuilds encoders from timm by name only; export a graft of "
                "a registry or timm: encoder (docs/EXPORT.md)")
    try:
        spec = get_spec(record.encoder)
    except Exception as err:  # noqa: BLE001 - a name this checkout no longer knows
        return f"its encoder {record.encoder!r} is unknown here ({type(err).__name__})"
    if spec.timm_name is None:
        return (f"its encoder {record.encoder!r} is a known-answer function, not a timm "
                "architecture: nothing for the plugin to rebuild")
    return None


def best_cell(results_dir: str | Path, backbone: str, suite: str) -> tuple[Record, str]:
    """The report's winner on `backbone` x `suite`: the best-ranked exportable encoder (lowest
    mean normalised MSE over seeds), its seed with the lowest MSE; and a line saying so."""
    from bench.analysis.rankings import rank_encoders

    results = results_of(results_dir)
    for option, name, present in (("BACKBONE", backbone, {r.backbone for r in results.records}),
                                  ("SUITE", suite, {r.suite for r in results.records})):
        if name not in present:  # a typo: name what is there, not a run to start
            close = difflib.get_close_matches(name, sorted(present), n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise ExportError(f"--best {backbone} {suite}: no {option.lower()} {name!r} in "
                              f"{results_dir}{hint}; {option.lower()}s there: "
                              f"{', '.join(sorted(present)) or 'none'}")
    ranking = rank_encoders(results.records, backbone, suite)
    if ranking.error:
        raise ExportError(f"no graft cells of {backbone} x {suite} in {results_dir}: run them "
                          f"first (pytest bench -k \"{backbone} and {suite}\")")
    for result in ranking.encoders:
        cells = [r for r in results.records if r.kind == GRAFT and r.backbone == backbone
                 and r.suite == suite and r.encoder == result.encoder]
        if cells and exportable(cells[0]):
            best = min(cells, key=lambda r: (r.mse_in(NORMALIZED), r.seed))
            note = (f"rank {result.rank} of {len(ranking.encoders)} on {backbone} x {suite} "
                    f"(mean normalised MSE {result.mean[NORMALIZED]:.4f} over seeds "
                    f"{result.seeds}); seed {best.seed} has its lowest MSE")
            if result.rank > 1:
                note += (f"; the leader {ranking.leader!r} is not a timm encoder and does not "
                         "export")
            return best, note
    raise ExportError(f"no graft encoder of {backbone} x {suite} is a timm architecture "
                      f"(ranked: {[e.encoder for e in ranking.encoders]}): nothing to export")
