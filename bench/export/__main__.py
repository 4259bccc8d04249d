"""python -m bench.export CELL_ID --results-dir DIR --out OUT
python -m bench.export --best BACKBONE SUITE --results-dir DIR --out OUT
python -m bench.export --list --results-dir DIR

Writes a LeRobot pretrained_model folder of a graft cell (bench.export). Bad input: one line on
stderr naming the thing and the fix, exit 4 (pytest bench's usage error), nothing written."""

from __future__ import annotations

import argparse
import sys

from bench.export.locate import ExportError
from bench.option_values import USAGE_ERROR, CommandParser

PROG = "python -m bench.export"


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    parser = CommandParser(prog=PROG, description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("cell_id", nargs="?", help="the graft cell to export")
    parser.add_argument("--best", nargs=2, metavar=("BACKBONE", "SUITE"),
                        help="export the report's winner on BACKBONE x SUITE instead")
    parser.add_argument("--results-dir", required=True, help="the results dir of the run")
    parser.add_argument("--out", help="the folder to write (must not exist)")
    parser.add_argument("--list", action="store_true", help="list every cell: the exportable ones with their MSE, the others with why not")
    args = parser.parse_args(argv)
    if not args.list and (bool(args.cell_id) == bool(args.best)):
        parser.error("name one CELL_ID or --best BACKBONE SUITE")
    if not args.list and not args.out:
        parser.error("--out OUT is required: the new checkpoint folder")
    return args


def list_cells(results_dir: str) -> int:
    """Every cell of the results dir, one line each: an exportable graft with its MSE, any
    other with why it cannot export (not a graft, its encoder, failed); a last line when none
    can."""
    from bench.export.locate import results_of, why_not_exportable
    from bench.grid.kinds import GRAFT

    results = results_of(results_dir)
    lines, exportable = [], 0
    for record in sorted(results.records, key=lambda r: r.cell_id):
        why = (why_not_exportable(record) if record.kind == GRAFT else
               f"a {record.kind} cell: only graft cells export")
        exportable += why is None
        lines.append(f"{record.cell_id}  mse {record.mse_in('normalized'):.6g}" if why is None
                     else f"{record.cell_id}  not exportable: {why}")
    lines += [f"{f.cell_id}  not exportable: it failed ({f.error})"
              for f in sorted(results.failed, key=lambda f: f.cell_id)]
    for line in lines:
        print(line)
    if not exportable:
        why = (f"{len(lines)} cell(s), none exportable" if lines else
               "no cells (run `pytest bench` with --results-dir there first)")
        print(f"bench.export: nothing to export in {results_dir}: {why}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    try:
        if args.list:
            return list_cells(args.results_dir)
        from bench.export.build import export_cell

        note = None
        cell_id = args.cell_id
        if args.best:
            from bench.export.locate import best_cell

            record, note = best_cell(args.results_dir, *args.best)
            cell_id = record.cell_id
        out = export_cell(args.results_dir, cell_id, args.out, note=note)
    except ExportError as err:  # bad input: exit 4, the usage error of every entry point
        print(f"bench.export: {err}", file=sys.stderr)
        return USAGE_ERROR
    print(f"bench.export: {cell_id} -> {out} (lerobot-train --policy.path={out} ...: see "
          f"{out}/README.md)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
