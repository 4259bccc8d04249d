"""May graftbench write here? The one owner of that rule, asked by every entry point before it
writes a file the user named or one that lands beside it: the report and its companions
(`pytest bench --report`, `python -m bench.report --report`), a saved baseline
(`--save-baseline`), an exported checkpoint folder (`python -m bench.export --out`).

Each check returns None (write) or the one line that refuses: the option, the value and the
fix. The caller raises it as its own usage error (exit 4), before anything is measured or
written. The rules:
- a report goes only where nothing is, or where a graftbench report is (recognised by the
  first line bench.report.build writes, never by the file's name), never inside a results
  folder's record tree (cells/, failed/, ...: the store's files), and each companion it writes
  beside itself (CSV, JSON, plots) must be graftbench's own or absent;
- a report that would hold fewer cells than the one it replaces needs `--replace-report`;
- a baseline is a NAME (no folder separator, no `..`, no `.json`), stored in --baseline-dir;
  replacing a saved one needs `--replace-baseline`;
- an export folder must not exist yet, nor lie in a record tree.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

# The first line of every report bench.report.build writes: the report's own marker.
REPORT_MARKER = "# graftbench report"
REPLACE_REPORT = "--replace-report"
REPLACE_BASELINE = "--replace-baseline"
_BASELINE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]*(\.[A-Za-z0-9_-]+)*$")


def report_companions(out: Path) -> dict[str, Path]:
    """The files build_report writes beside `out`: {what: path} (bench.report.build)."""
    return {"CSV": out.parent / f"{out.stem}_cells.csv",
            "summary JSON": out.parent / f"{out.stem}_summary.json",
            "plots folder": out.parent / f"{out.stem}_plots"}


def record_folders() -> tuple[str, ...]:
    """The folders of a results dir that hold its records and their working files."""
    from bench.cell.projectors import PROJECTORS
    from bench.results.robust import ROBUST
    from bench.results.store import CELLS, CLAIMS, FAILED, ROLLOUTS, SCREENS, UNREADABLE

    return (CELLS, FAILED, SCREENS, ROLLOUTS, CLAIMS, UNREADABLE, PROJECTORS, ROBUST, "submitit")


def in_record_tree(path: Path) -> Path | None:
    """The results dir whose record tree holds `path` (None: none does). A results dir is a
    folder holding cells/ (the store makes it); its record tree, the folders record_folders
    names."""
    from bench.results.store import CELLS

    path = Path(os.path.abspath(path))  # `..` folded: results/cells/../R.md is results/R.md
    folders = record_folders()
    for below, folder in zip(path.parents, list(path.parents)[1:]):
        if below.name in folders and (folder / CELLS).is_dir():
            return folder
    return None


def is_graftbench_report(path: Path) -> bool:
    """Whether `path` is a file whose first line is the report's marker."""
    try:
        with open(path, encoding="utf-8") as f:
            return f.readline().rstrip("\n") == REPORT_MARKER
    except (OSError, UnicodeDecodeError):
        return False


def _is_companion(what: str, path: Path) -> bool:
    """Whether an existing companion file is one build_report wrote."""
    if what == "plots folder":
        return path.is_dir() and all(p.suffix == ".png" for p in path.iterdir())
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return False
    if what == "CSV":
        return text.startswith("cell_id,status,")
    try:
        data = json.loads(text)
    except ValueError:
        return False
    return isinstance(data, dict) and "answer" in data and "cells" in data


def report_cells(out: Path) -> int | None:
    """How many cells (finished and failed) the report at `out` holds, from its summary JSON;
    None when unknown."""
    try:
        cells = json.loads(report_companions(out)["summary JSON"].read_text())["cells"]
        return int(cells["finished"]) + len(cells["failed"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def report_refusal(option: str, out: str | Path, *, cells_after: int | None = None,
                   replace: bool = False) -> str | None:
    """Why the report may not be written at `out` (as typed: `report_folder_refusal`; None: it
    may). `cells_after`: how many cells the new report will hold at most, checked against the one
    it replaces unless `replace`."""
    from bench.option_values import report_folder_refusal

    folder = report_folder_refusal(option, out)
    if folder:
        return folder
    out = Path(out)
    results = in_record_tree(out)
    if results is not None:
        return (f"{option} {out}: inside the record tree of the results dir {results}, where "
                f"the store keeps its records; fix: {option} {results / 'REPORT.md'}, or a path "
                "outside it")
    if out.exists() and not is_graftbench_report(out):
        new = out.with_name("REPORT.md" if out.name != "REPORT.md" else "REPORT-new.md")
        return (f"{option} {out}: the file exists and is not a graftbench report (its first "
                f"line is not {REPORT_MARKER!r}), so it is left as it is; fix: name a new file, "
                f"e.g. {option} {new}")
    for what, path in report_companions(out).items():
        if path.exists() and not _is_companion(what, path):
            return (f"{option} {out}: the report's {what} would replace {path}, which graftbench "
                    "did not write; fix: name a report whose companions are free (e.g. "
                    f"{option} {out.with_name(out.stem + '-report.md')})")
    held = report_cells(out) if out.exists() else None
    if not replace and cells_after is not None and held is not None and cells_after < held:
        return (f"{option} {out}: the report there holds {held} cell(s) and this one would hold "
                f"at most {cells_after}; fix: add {REPLACE_REPORT} to replace it with fewer, or "
                f"name another file with {option}")
    return None


def baseline_name_refusal(option: str, name: str) -> str | None:
    """Why `name` is not a baseline name (None: it is): a name, never a path."""
    if _BASELINE_NAME.match(name) and not name.endswith(".json"):
        return None
    stem = Path(name).name.removesuffix(".json")
    stem = re.sub(r"[^A-Za-z0-9._-]", "-", stem).strip(".-") or "ci"
    return (f"{option} {name}: a baseline is a NAME (letters, digits, '_', '-', '.'; no folder "
            f"separator, '..' or .json), stored as NAME.json in --baseline-dir; fix: "
            f"{option} {stem} (add --baseline-dir DIR for another folder)")


def baseline_refusal(option: str, name: str, folder: Path, replace: bool) -> str | None:
    """Why the baseline `name` may not be saved in `folder` (None: it may)."""
    problem = baseline_name_refusal(option, name)
    if problem:
        return problem
    path = Path(folder) / f"{name}.json"
    if path.exists() and not replace:
        return (f"{option} {name}: {path} exists; fix: add {REPLACE_BASELINE} to replace it, "
                f"or save under another name")
    return None


def export_refusal(option: str, out: Path) -> str | None:
    """Why an export folder may not be written at `out` (None: it may)."""
    out = Path(out)
    if out.exists():
        return (f"{option} {out} already exists; fix: name a new folder (an export never "
                "overwrites)")
    results = in_record_tree(out)
    if results is not None:
        return (f"{option} {out}: inside the record tree of the results dir {results}; fix: "
                "name a folder outside it")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                return f"{option} {out}: {parent} is a file; fix: name a folder in a folder"
            break
    return None
