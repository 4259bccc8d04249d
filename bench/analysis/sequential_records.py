"""The sequential design (bench.analysis.sequential) read from a results folder's cell records.

    python -m bench.analysis.sequential_records RESULTS --alpha 0.05 --budget 3000 \\
        --per-task 1 [--cells ID,ID,...] [--by-item [--items NAME,NAME,...]] [--unplanned ignore]

Each cell with rollouts is an item. Its episode e of LIBERO task t is unit
`tasks.index(t) * per_task + e % per_task` of round `e // per_task`: a round is `per_task`
episodes of every task, the same init states for every item (paired). With `--by-item` an item
is what a cell is, seeds and releases aside (bench.grid.kinds.record_label: an encoder, native):
its cells are blocks of units, block b the b-th (release, seed) every item has, so a round is
`per_task` episodes of every task in every cell, paired across items by release, seed, task and
init state. Prints one JSON object: the design, the order with each adjacent pair's evidence, and
the next round (each item's episodes per task to roll out, i.e. its next `--rollouts`) or why the
study stops. `--unplanned ignore` replays records rolled out uniformly as the design would have
spent them.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from bench.analysis.sequential import SequentialDesign, next_round, study_state, study_summary


def rows_of(item: str, rollouts: dict, per_task: int, block: int = 0) -> list[dict]:
    """A record's rollout episodes as the design's rows (item, round, unit, success); `block`:
    which of an item's cells (release, seed) they are (0 for a cell that is its own item)."""
    tasks = list(rollouts["spec"]["tasks"])
    first = block * len(tasks)
    return [{"item": item, "round": e["episode"] // per_task,
             "unit": (first + tasks.index(e["task"])) * per_task + e["episode"] % per_task,
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
    return items, rows, _one_task_list(tasks)


def _one_task_list(tasks: set) -> tuple:
    if len(tasks) > 1:
        raise SystemExit(f"the cells were rolled out on different tasks {sorted(tasks)}: "
                         "their episodes are not paired")
    return next(iter(tasks)) if tasks else ()


@dataclass(frozen=True)
class ItemStudy:
    """A results folder's items as the design sees them with --by-item: each item's cells
    (one per (release, seed) block, the same blocks for every item), rows and tasks."""

    items: list[str]
    cells: dict[str, list[str]]  # item -> its cell ids, in block order
    blocks: list[tuple[int, int]]  # (release, seed) of each block
    rows: list[dict]
    tasks: tuple  # () when no cell has rollouts yet
    episodes: dict[str, int]  # item -> episodes per task its cells hold (the least of them)


def item_study(results: Path, per_task: int, items: list[str] | None = None,
               backbone: str | None = None, suite: str | None = None) -> ItemStudy:
    """The items (all labels with rollouts, or `items`, rolled out or not) of a results folder,
    of one backbone x suite (the only one, or the one named)."""
    from bench.grid.kinds import record_label
    from bench.results.store import load_results

    records = [r for r in load_results(results).records
               if backbone in (None, r.backbone) and suite in (None, r.suite)]
    where = {(r.backbone, r.suite) for r in records if items is None or record_label(r) in items}
    if len(where) > 1:
        raise SystemExit(f"cells of {sorted(where)}: name one backbone and suite")
    groups: dict[str, list] = {}
    for r in records:
        if items is None and (r.run.rollouts or {}).get("episodes") or \
                items is not None and record_label(r) in items:
            groups.setdefault(record_label(r), []).append(r)
    chosen = items if items is not None else sorted(groups)
    absent = [i for i in chosen if i not in groups]
    if absent:
        raise SystemExit(f"{results}: no record of item(s) {absent}: measure them first")
    blocks = sorted({(int(r.release), int(r.seed)) for g in groups.values() for r in g})
    rows, tasks, cells, episodes = [], set(), {}, {}
    for item in chosen:
        slots = {(int(r.release), int(r.seed)): r for r in groups[item]}
        if sorted(slots) != blocks:
            raise SystemExit(f"{item} has cells (release, seed) {sorted(slots)}, the items "
                             f"together {blocks}: --by-item pairs items block by block")
        cells[item] = [slots[b].cell_id for b in blocks]
        held = []
        for b, block in enumerate(blocks):
            rollouts = slots[block].run.rollouts or {}
            held.append(rollouts["spec"]["episodes_per_task"] if rollouts.get("episodes") else 0)
            if rollouts.get("episodes"):
                tasks.add(tuple(rollouts["spec"]["tasks"]))
                rows += rows_of(item, rollouts, per_task, b)
        episodes[item] = min(held)
    return ItemStudy(list(chosen), cells, blocks, rows, _one_task_list(tasks), episodes)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.analysis.sequential_records",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("results", type=Path)
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--budget", type=int, required=True, help="episodes for the whole study")
    p.add_argument("--per-task", type=int, default=1, help="episodes per task in a round")
    p.add_argument("--cells", help="comma list of cell ids (default: every cell with rollouts)")
    p.add_argument("--by-item", action="store_true",
                   help="an item is an encoder or native, its cells blocks of units")
    p.add_argument("--items", help="comma list of items (with --by-item; default: all rolled out)")
    p.add_argument("--unplanned", choices=("refuse", "ignore"), default="refuse")
    a = p.parse_args(argv)
    if a.by_item:
        study = item_study(a.results, a.per_task, [i for i in (a.items or "").split(",") if i]
                           or None)
        items, rows, tasks, blocks = study.items, study.rows, study.tasks, len(study.blocks)
    else:
        cells = [c for c in (a.cells or "").split(",") if c] or None
        (items, rows, tasks), blocks = study_rows(a.results, a.per_task, cells), 1
    if len(items) < 2:
        raise SystemExit(f"{a.results}: {len(items)} item(s) with rollouts; the design orders 2+")
    design = SequentialDesign(a.alpha, a.budget, a.per_task * len(tasks) * blocks)
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
