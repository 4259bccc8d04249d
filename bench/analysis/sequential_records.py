"""The sequential design (bench.analysis.sequential) read from a results folder's cell records.

    python -m bench.analysis.sequential_records RESULTS --alpha 0.05 --budget 3000 \\
        --per-task 1 [--cells ID,ID,...] [--unplanned ignore]

Each cell with rollouts is an item. Its episode e of LIBERO task t is unit
`tasks.index(t) * per_task + e % per_task` of round `e // per_task`: a round is `per_task`
episodes of every task, the same init states for every item (paired). Prints one JSON object:
the design, the order with each adjacent pair's evidence, and the next round (each item's
episodes per task to roll out, i.e. its next `--rollouts`) or why the study stops.
`--unplanned ignore` replays records rolled out uniformly as the design would have spent them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from bench.analysis.sequential import SequentialDesign, next_round, study_state, study_summary


def rows_of(cell_id: str, rollouts: dict, per_task: int) -> list[dict]:
    """A record's rollout episodes as the design's rows (item, round, unit, success)."""
    tasks = list(rollouts["spec"]["tasks"])
    return [{"item": cell_id, "round": e["episode"] // per_task,
             "unit": tasks.index(e["task"]) * per_task + e["episode"] % per_task,
             "success": bool(e["success"])} for e in rollouts["episodes"]]


def study_rows(results: Path, per_task: int, cells: list[str] | None = None):
    """(items, rows, tasks) of the results folder's cells with rollouts (all, or `cells`)."""
    from bench.results.store import ResultStore

    store = ResultStore(results)
    ids = cells or sorted(p.stem for p in (results / "cells").glob("*.json"))
    items, rows, tasks = [], [], set()
    for cell_id in ids:
        record = store.load(cell_id)
        rollouts = record.run.rollouts if record is not None else None
        if not rollouts or "episodes" not in rollouts:
            if cells:
                raise SystemExit(f"{cell_id}: no rollouts stored under {results}")
            continue
        items.append(cell_id)
        tasks.add(tuple(rollouts["spec"]["tasks"]))
        rows += rows_of(cell_id, rollouts, per_task)
    if len(tasks) > 1:
        raise SystemExit(f"the cells were rolled out on different tasks {sorted(tasks)}: "
                         "their episodes are not paired")
    return items, rows, (next(iter(tasks)) if tasks else ())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.analysis.sequential_records",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("results", type=Path)
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--budget", type=int, required=True, help="episodes for the whole study")
    p.add_argument("--per-task", type=int, default=1, help="episodes per task in a round")
    p.add_argument("--cells", help="comma list of cell ids (default: every cell with rollouts)")
    p.add_argument("--unplanned", choices=("refuse", "ignore"), default="refuse")
    a = p.parse_args(argv)
    cells = [c for c in (a.cells or "").split(",") if c] or None
    items, rows, tasks = study_rows(a.results, a.per_task, cells)
    if len(items) < 2:
        raise SystemExit(f"{a.results}: {len(items)} cell(s) with rollouts; the design orders 2+")
    design = SequentialDesign(a.alpha, a.budget, a.per_task * len(tasks))
    state, _ = study_state(design, items, rows, unplanned=a.unplanned)
    plan = next_round(design, items, rows, a.unplanned)
    out = study_summary(design, items, state)
    out["next"] = {"stop": plan["stop"], "round": plan["round"],
                   "rollouts": {item: (plan["round"] + 1) * a.per_task for item in plan["run"]}}
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
