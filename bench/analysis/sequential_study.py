"""A sequential closed-loop study run in rounds of `pytest bench ... --rollouts N`.

    python -m bench.analysis.sequential_study RESULTS --items native,effnet_lite0,... \\
        --backbone pi05 --suite spatial --tasks 0,1,2,3 --per-task 3 --max-per-task 21 \\
        --budget 1500 --alpha 0.05 [--dry-run] -- PYTEST_ARGS

PYTEST_ARGS: the study's grid file and options (--results-dir, --rollouts and -k are the
runner's). Each round reads the records (every item's cells and their episodes:
bench.analysis.sequential_records `item_study`, an item an encoder or native, its cells blocks of
units), replays the design (bench.analysis.sequential) and runs the next round as one pytest
command that selects the cells of every item the round runs (-k "<backbone>-<suite>-<item>- or
..."), all with the round's `--rollouts (round + 1) * per_task`: a stored cell keeps its episodes
and rolls out only the new ones, nothing retrained (bench.cell.extend). One command, not one per
item, so the round's cells share one process: its start-up, and the rollout workers with their
envs (bench.sim.workers keeps them across a process's cells), are paid once a round. It stops
when the design does (every adjacent pair declared, or the next round would overspend the
budget), when the next round would pass `--max-per-task` (demonstrations hold the first init
states of a task: start-up refuses --rollouts beyond 50 - their count), when the episodes the
study rolled out would pass the budget, or when the command fails (the items' records say why;
rerun to continue).

The design is declared once: RESULTS/sequential.json (DESIGN_FILE) holds it with the items,
tasks and blocks, and each round (its items and their --rollouts, or the items of a failed
command and its exit status) as it ends; a rerun with another design is refused, one with the
same continues where the last stopped (a round in flight included: cells already extended
resume, the items it finished are left out of the rerun's command). An item that sat rounds out and is run again (racing brings an item back when
its neighbours' order changes) rolls out the rounds it missed too (--rollouts counts from the
first episode): the design leaves those rows out (a row it did not choose is no evidence,
`unplanned="ignore"`), the budget counts them (it is of episodes rolled out).
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

from bench.analysis.sequential import SequentialDesign, next_round, study_state, study_summary
from bench.analysis.sequential_records import ItemStudy, item_study
from bench.grid.kinds import NATIVE
from bench.option_values import CommandParser, refuse, whole_at_least

DESIGN_FILE = "sequential.json"
IGNORE = "ignore"  # rows the design did not choose (an item's missed rounds) are left out


@dataclass(frozen=True)
class Study:
    """What a sequential study is declared with, besides its design."""

    results: Path
    items: tuple[str, ...]
    backbone: str
    suite: str
    tasks: tuple[int, ...]
    per_task: int  # episodes per task and cell in a round
    max_per_task: int  # the most episodes per task a cell may roll out
    blocks: int  # cells per item (release x seed)

    def declared(self, design: SequentialDesign) -> dict:
        """The declaration stored in DESIGN_FILE (and compared on a rerun)."""
        study = {k: v for k, v in asdict(self).items() if k != "results"}
        return {"design": design.as_dict(), "study": json.loads(json.dumps(study))}


@dataclass(frozen=True)
class Round:
    """The next round: its index, each item's --rollouts, or why the study stops."""

    index: int
    rollouts: dict[str, int]
    stop: str | None
    summary: dict
    spent: int  # episodes the items' records hold (all rounds, all cells)


def plan_round(study: Study, design: SequentialDesign, progress: ItemStudy) -> Round:
    """The design's next round from the records, with the runner's own stops (init states,
    the budget of episodes rolled out)."""
    items = list(study.items)
    if progress.tasks and tuple(progress.tasks) != tuple(study.tasks):
        raise SystemExit(f"the records were rolled out on tasks {progress.tasks}, the study "
                         f"declares {study.tasks}")
    state, _ = study_state(design, items, progress.rows, unplanned=IGNORE)
    plan = next_round(design, items, progress.rows, unplanned=IGNORE)
    summary = study_summary(design, items, state)
    per_cell = len(study.tasks) * study.blocks
    spent = sum(progress.episodes[i] for i in items) * per_cell
    wanted = (plan["round"] + 1) * study.per_task
    # a round in flight names the items whose cells it finished too (no unit left): not rerun
    rollouts = {item: wanted for item, units in plan["run"].items() if units}
    stop = plan["stop"]
    cost = sum(wanted - progress.episodes[i] for i in rollouts) * per_cell
    if stop is None and wanted > study.max_per_task:
        stop = f"init states: round {plan['round']} needs {wanted} episodes per task, the " \
               f"suite leaves {study.max_per_task}"
    elif stop is None and spent + cost > design.budget:
        stop = f"budget: {spent} episodes rolled out, the next round {cost} more"
    return Round(plan["round"], {} if stop else rollouts, stop, summary, spent)


def cell_pattern(cell_id: str) -> str:
    """The -k expression of an item's cells from one of its ids: the id without its release and
    seed, ending in '-' (pi05-spatial-native-rel1-seed0 -> pi05-spatial-native-)."""
    return re.sub(r"(-rel\d+)?-seed\d+$", "-", cell_id)


def round_command(study: Study, progress: ItemStudy, rollouts: dict[str, int],
                  pytest_args: Sequence[str], python: str = sys.executable) -> list[str]:
    """The one pytest command of a round: every item's cells, at the round's --rollouts."""
    counts = set(rollouts.values())
    if len(counts) != 1:  # plan_round gives every item of a round the same count
        raise ValueError(f"a round's items need one --rollouts for one command: {rollouts}")
    selected = " or ".join(cell_pattern(progress.cells[item][0]) for item in rollouts)
    return [python, "-m", "pytest", "bench", *pytest_args, "--results-dir", str(study.results),
            "--rollouts", str(counts.pop()), "-k", selected]


def order_line(summary: dict) -> str:
    """'a > b ~ c': the order, '>' where the pair is declared."""
    pairs = summary["pairs"]
    if not pairs:
        return " ".join(summary["order"])
    return summary["order"][0] + "".join((" > " if p["declared"] else " ~ ") + p["lower"]
                                         for p in pairs)


def check_declared(path: Path, declared: dict) -> dict:
    """The stored study file (its rounds kept), or a new one; SystemExit when the folder holds
    a study declared otherwise."""
    if not path.is_file():
        return {**declared, "rounds": []}
    stored = json.loads(path.read_text())
    for key in ("design", "study"):
        if stored.get(key) != declared[key]:
            raise SystemExit(f"{path}: the study there was declared with {key} "
                             f"{stored.get(key)}, not {declared[key]}: continue it with the "
                             "same options, or give another results folder")
    return stored


def run_study(study: Study, design: SequentialDesign, pytest_args: Sequence[str], *,
              execute: Callable[[list[str]], int] | None = None, dry_run: bool = False,
              say: Callable[[str], None] = print) -> Round:
    """Rounds until a stop (module docstring); the last Round. `execute(command) -> exit
    status` runs a round's pytest command (a subprocess unless a test passes its own);
    `dry_run`: print the next round's command, run and write nothing."""
    execute = execute or (lambda cmd: subprocess.run(cmd, check=False).returncode)
    path = study.results / DESIGN_FILE
    stored = check_declared(path, study.declared(design))
    while True:
        progress = item_study(study.results, study.per_task, list(study.items),
                              study.backbone, study.suite)
        nxt = plan_round(study, design, progress)
        say(f"[sequential] after {nxt.summary['rounds']} round(s): {order_line(nxt.summary)}; "
            f"{nxt.spent} episodes rolled out of {design.budget}")
        if not dry_run:
            stored["last"] = {**nxt.summary, "stop": nxt.stop, "spent_episodes": nxt.spent}
            _write(path, stored)
        if nxt.stop:
            say(f"[sequential] stopped: {nxt.stop}")
            return nxt
        cmd = round_command(study, progress, nxt.rollouts, pytest_args)
        items = ", ".join(f"{item} (--rollouts {n})" for item, n in nxt.rollouts.items())
        say(f"[sequential] round {nxt.index}, {len(nxt.rollouts)} item(s) {items}: "
            f"{shlex.join(cmd)}")
        if dry_run:
            return nxt
        status = execute(cmd)
        if status != 0:
            stored["rounds"].append({"round": nxt.index, "failed": list(nxt.rollouts),
                                     "episodes_per_task": nxt.rollouts, "exit_status": status})
            _write(path, stored)
            raise SystemExit(f"[sequential] round {nxt.index} ({', '.join(nxt.rollouts)}) exited "
                             f"{status} (the records or failure files say why); rerun this "
                             "command to continue the round")
        stored["rounds"].append({"round": nxt.index, "episodes_per_task": nxt.rollouts})
        _write(path, stored)


def _write(path: Path, data: dict) -> None:
    from bench.results.store import atomic_write_json

    atomic_write_json(path, data)


PROG = "python -m bench.analysis.sequential_study"


def _ints(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        values = ()
    if not values or min(values) < 0:
        refuse(PROG, f"--tasks {text!r}: give the LIBERO task ids as a comma list, e.g. 0,1,2,3 "
                     "(the offline run's --sim-tasks)")
    return values


def check_arguments(a: argparse.Namespace) -> tuple[str, ...]:
    """Every argument checked before a record is read: one line naming the argument, its value
    and the fix (exit USAGE_ERROR). Returns the items."""
    from backbones import get_entry
    from encoders.base import UnknownEncoder
    from encoders.registry import get_spec, is_user_encoder

    if not a.results.is_dir():
        refuse(PROG, f"{a.results}: no such folder; give the results folder of the study's "
                     "offline run (its --results-dir, the one that holds cells/)")
    items = tuple(i.strip() for i in a.items.split(",") if i.strip())
    if len(items) < 2 or len(set(items)) != len(items):
        refuse(PROG, f"--items {a.items!r}: give two or more distinct items, each an encoder or "
                     "native, e.g. native,effnet_lite0,effnet_lite1")
    for item in items:
        if item == NATIVE or is_user_encoder(item):
            continue
        try:
            get_spec(item)
        except UnknownEncoder as e:
            refuse(PROG, f"--items {item!r}: an item is native or an encoder: {e}")
    try:
        get_entry(a.backbone)
    except ValueError as e:
        refuse(PROG, f"--backbone: {e}")
    if not 0 < a.alpha < 1:
        refuse(PROG, f"--alpha {a.alpha}: give a level in (0, 1), e.g. 0.05")
    if a.max_per_task < a.per_task:
        refuse(PROG, f"--max-per-task {a.max_per_task} is below --per-task {a.per_task}: no round "
                     "would fit; give --max-per-task >= --per-task (at most 50 - the demos' "
                     "init states, e.g. 21)")
    return items


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, pytest_args = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) \
        if "--" in argv else (argv, [])
    p = CommandParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("results", type=Path)
    p.add_argument("--items", required=True, help="comma list: encoders and native")
    p.add_argument("--backbone", required=True)
    p.add_argument("--suite", required=True)
    p.add_argument("--tasks", required=True, help="the LIBERO task ids (--sim-tasks)")
    p.add_argument("--per-task", type=whole_at_least(1, "3"), default=1,
                   help="episodes per task and cell a round")
    p.add_argument("--max-per-task", type=whole_at_least(1, "21"), default=21,
                   help="episodes per task a cell may roll out (50 - the demos' init states)")
    p.add_argument("--budget", type=whole_at_least(1, "900"), required=True,
                   help="episodes for the whole study")
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--dry-run", action="store_true", help="print the next round's command")
    a = p.parse_args(ours)
    items = check_arguments(a)
    tasks = _ints(a.tasks)
    blocks = len(item_study(a.results, a.per_task, list(items), a.backbone, a.suite).blocks)
    study = Study(a.results, items, a.backbone, a.suite, tasks, a.per_task, a.max_per_task,
                  blocks)
    design = SequentialDesign(a.alpha, a.budget, a.per_task * len(tasks) * blocks)
    run_study(study, design, pytest_args, dry_run=a.dry_run)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
