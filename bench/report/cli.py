"""`python -m bench.report RESULTS_DIR [--report OUT] [--resamples N] [--no-plots]`: rebuild
REPORT.md from stored records (bench.report.build).

Every input is checked before anything is written: a folder that holds no records is refused
(the report, its CSV and JSON beside it are left as they were, never overwritten with "No
finished cells"), and so are a file given as the folder, a replicate count below 2, a record
that cannot be read (unless --skip-unreadable: the report then holds what was readable and the
terminal names what was not), and a report path bench.outputs does not allow (a folder, a file
that is not a graftbench report, the record tree, fewer cells than the report there holds
without --replace-report). Bad input is one line on stderr with the fix, exit 4 (pytest bench's
usage error).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from bench.option_values import CommandParser, refuse, whole_at_least
from ondisk.paths import unwritable

PROG = "python -m bench.report"
LEAST_RESAMPLES = 2  # one replicate has no spread: every interval would be NaN


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = CommandParser(prog=PROG, description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results_dir", type=Path, help="results dir holding cells/ (and grid.json)")
    # --report, as in `pytest bench --report PATH`; --out kept for older commands.
    parser.add_argument("--report", "--out", dest="out", default=None,  # as typed: a trailing /
                        help="report path (default: RESULTS_DIR/REPORT.md)")
    # No default here: bench.analysis.rankings (scipy) loads only once the input is checked.
    parser.add_argument("--resamples", type=whole_at_least(LEAST_RESAMPLES, "2000"),
                        help="bootstrap replicates (default: bench.analysis.rankings's, 2000)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    parser.add_argument("--skip-unreadable", action="store_true",
                        help="write the report from the readable records when some cannot be "
                             "read (default: stop, naming them, the existing report kept)")
    parser.add_argument("--replace-report", action="store_true",
                        help="replace a report that holds more cells than this one will")
    return parser.parse_args(argv)


def results_folders_below(folder: Path, limit: int = 3) -> list[Path]:
    """Folders one or two levels below `folder` that hold cells/: what the user likely meant
    (`.graftbench/results` is one level above a results dir)."""
    found = [p.parent for p in sorted(folder.glob("*/cells")) + sorted(folder.glob("*/*/cells"))
             if p.is_dir()]
    return found[:limit]


def check_results_dir(folder: Path):
    """The folder's Results, or a refusal naming why it holds no report's worth of records."""
    from bench.results.store import load_results

    if not folder.exists():
        refuse(PROG, f"RESULTS_DIR {folder}: no such folder; fix: pass the --results-dir of a "
                     "`pytest bench` run (default .graftbench/results/<profile>)")
    if not folder.is_dir():
        refuse(PROG, f"RESULTS_DIR {folder}: a file, not a folder; fix: pass the folder that "
                     "holds cells/")
    results = load_results(folder)
    if results.records or results.failed or results.screens or results.screen_failures:
        return results
    below = results_folders_below(folder)
    hint = (f"; results dirs below it: {', '.join(map(str, below))}" if below else
            "; fix: pass the --results-dir of a `pytest bench` run")
    why = (f"no readable record ({len(results.skipped)} unreadable file(s) skipped: "
           f"{_skipped_text(results.skipped)})" if results.skipped else "no records (no cells/ or "
           "failed/ *.json)")
    refuse(PROG, f"RESULTS_DIR {folder}: {why}; nothing written, existing reports left as they "
                 f"were{hint}")


def check_out(typed: str | Path, results, replace: bool) -> Path:
    """The report path (`typed`: as given), by the one rule of bench.outputs: refused in one
    line, nothing written."""
    from bench.outputs import report_refusal

    problem = report_refusal("--report", typed, cells_after=len(results.records) +
                             len(results.failed), replace=replace)
    if problem:
        refuse(PROG, problem)
    out = Path(typed)
    problem = unwritable(out.parent)  # made now: a refusal here beats a traceback at the end
    if problem:
        refuse(PROG, f"--report {out}: {out.parent}: {problem}; give a path in a folder you can "
                     "write")
    return out


def check_readable(folder: Path, results, skip: bool) -> None:
    """Records that cannot be read stop the report (it would shrink without a word), unless
    the user asked to write what was readable."""
    if results.skipped and not skip:
        refuse(PROG, f"RESULTS_DIR {folder}: {len(results.skipped)} record file(s) cannot be "
                     f"read: {_skipped_text(results.skipped)}; nothing written, the existing "
                     "report kept; fix: repair or remove them, or add --skip-unreadable to "
                     "report the readable ones")


def _skipped_text(skipped: list[tuple[str, str]], shown: int = 3) -> str:
    text = "; ".join(f"{path} ({reason})" for path, reason in skipped[:shown])
    return text + (f"; and {len(skipped) - shown} more" if len(skipped) > shown else "")


def main(argv: Sequence[str] | None = None) -> int:
    args = parse(argv)
    results = check_results_dir(args.results_dir)
    check_readable(args.results_dir, results, args.skip_unreadable)
    out = check_out(args.out if args.out is not None else args.results_dir / "REPORT.md", results,
                    args.replace_report)
    from bench.report.build import build_report  # the analyses' imports: only once checked

    from bench.analysis.rankings import DEFAULT_RESAMPLES

    resamples = DEFAULT_RESAMPLES if args.resamples is None else args.resamples
    path = build_report(args.results_dir, out, n_resamples=resamples,
                        plots=not args.no_plots)
    print(f"wrote {path} ({len(results.records)} finished, {len(results.failed)} failed cell(s))")
    if results.skipped:
        print(f"{PROG}: skipped {len(results.skipped)} unreadable file(s), not in the report: "
              f"{_skipped_text(results.skipped)}", file=sys.stderr)
    return 0
