"""The sequential study's runner (bench.analysis.sequential_study) without the simulator: a fake
`pytest` grows the cells its -k selects (pytest's own -k expression, matched as pytest matches a
cell's id) from planted success rates, so the rounds, their one command each, the stops, the
declaration and resuming after a failed command are checked. ~3 s."""

from __future__ import annotations

import json
import zlib

import pytest
from _pytest.mark.expression import Expression

from bench.analysis.sequential import SequentialDesign
from bench.analysis.sequential_study import (DESIGN_FILE, Study, cell_pattern, main,
                                             run_study)
from bench.grid.kinds import cell_id
from bench.results.store import ResultStore, load_results
from tests.factories import make_record

TRUTH = {"native": 0.95, "effnet_lite0": 0.5, "effnet_lite0_random": 0.05}
TASKS = (0, 1)
# In the results folder, not in the study: its ids start like effnet_lite0's, no round may run it.
BYSTANDER = "effnet_lite0_s4"


def offline_study(root) -> ResultStore:
    """Each item's two cells (releases 0 and 1, seed 0) as the offline study leaves them, and the
    bystander's."""
    store = ResultStore(root)
    for item in (*TRUTH, BYSTANDER):
        kind, encoder = ("native", None) if item == "native" else ("graft", item)
        for release in (0, 1):
            store.write(make_record(kind=kind, backbone="pi05", encoder=encoder).replace(
                release=release, cell_id=cell_id(kind, "pi05", "spatial", encoder, 0, None,
                                                 release)))
    return store


def selected(root, cmd: list[str]) -> list:
    """The records of the cells a command's -k selects (pytest: a substring of the id)."""
    expression = Expression.compile(cmd[cmd.index("-k") + 1])
    return [r for r in load_results(root).records
            if expression.evaluate(lambda sub, **_: sub.lower() in r.cell_id.lower())]


def fake_pytest(root, calls: list, fail: tuple | None = None):
    """`execute(cmd)`: roll the -k-selected cells out to --rollouts N per task, success drawn
    from TRUTH per (item, release, task, episode); exit 1 at call `fail[0]` (after `fail[1]`
    of its cells are written: a kill mid-round)."""
    def execute(cmd: list[str]) -> int:
        calls.append(cmd)
        n = int(cmd[cmd.index("--rollouts") + 1])
        store = ResultStore(root)
        cells = sorted(selected(root, cmd), key=lambda r: r.cell_id)
        for k, record in enumerate(cells):
            if fail is not None and len(calls) == fail[0] and k == fail[1]:
                return 1
            item = record.encoder or "native"
            episodes = [{"task": t, "episode": e, "init_state": 49 - e, "steps": 50,
                         "success": zlib.crc32(f"{item}{record.release}{t}{e}".encode()) % 100
                         < 100 * TRUTH[item]} for t in TASKS for e in range(n)]
            store.write(record.replace(rollouts={
                "spec": {"tasks": list(TASKS), "episodes_per_task": n}, "episodes": episodes}))
        return 0

    return execute


def declared(root, budget: int = 2000):
    study = Study(root, tuple(TRUTH), "pi05", "spatial", TASKS, per_task=2, max_per_task=20,
                  blocks=2)
    return study, SequentialDesign(alpha=0.1, budget=budget, units_per_round=2 * 2 * 2)


def test_cell_patterns_select_an_items_cells_only():
    assert cell_pattern("pi05-spatial-native-rel1-seed0") == "pi05-spatial-native-"
    assert cell_pattern("pi05-spatial-effnet_lite0-seed1") == "pi05-spatial-effnet_lite0-"


def test_rounds_run_until_every_neighbour_pair_is_declared(tmp_path):
    offline_study(tmp_path)
    calls, lines = [], []
    last = run_study(*declared(tmp_path), ["--grid", "g.toml"],
                     execute=fake_pytest(tmp_path, calls), say=lines.append)
    assert last.stop == "resolved"
    assert last.summary["order"] == ["native", "effnet_lite0", "effnet_lite0_random"]
    assert calls[0][-6:] == ["--results-dir", str(tmp_path), "--rollouts", "2", "-k",
                             "pi05-spatial-native- or pi05-spatial-effnet_lite0- or "
                             "pi05-spatial-effnet_lite0_random-"]
    assert calls[0][3:6] == ["bench", "--grid", "g.toml"]
    # one command a round, selecting both cells of each item the round runs and nothing else,
    # at the round's --rollouts: 2 more episodes per task each round; racing runs fewer items
    rounds = json.loads((tmp_path / DESIGN_FILE).read_text())["rounds"]
    assert [r["round"] for r in rounds] == list(range(len(rounds))) and len(calls) == len(rounds)
    for cmd, r in zip(calls, rounds):
        assert set(r["episodes_per_task"].values()) == {2 * (r["round"] + 1)}
        assert cmd[cmd.index("--rollouts") + 1] == str(2 * (r["round"] + 1))
        cells = [(rec.encoder or "native", rec.release) for rec in selected(tmp_path, cmd)]
        assert sorted(cells) == sorted((item, release) for item in r["episodes_per_task"]
                                       for release in (0, 1))
    assert sum(len(r["episodes_per_task"]) for r in rounds) < 3 * len(rounds)  # racing
    assert lines[1].startswith("[sequential] round 0, 3 item(s) native (--rollouts 2), "
                               "effnet_lite0 (--rollouts 2), effnet_lite0_random (--rollouts 2):")
    assert lines[-1] == "[sequential] stopped: resolved"
    stored = [r for r in load_results(tmp_path).records if r.encoder != BYSTANDER]
    assert last.spent == sum(len(r.run.rollouts["episodes"]) for r in stored)
    assert not any(r.run.rollouts for r in load_results(tmp_path).records
                   if r.encoder == BYSTANDER)


def test_a_failed_command_stops_and_a_rerun_continues_to_the_same_study(tmp_path):
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    for root in (whole, broken):
        offline_study(root)
    run_study(*declared(whole), [], execute=fake_pytest(whole, []), say=lambda line: None)
    calls = []
    # round 1's command killed after 3 of its 6 cells (by id: effnet_lite0's two, one of the
    # random twin's)
    with pytest.raises(SystemExit, match=r"round 1 \(native, effnet_lite0, effnet_lite0_random"
                                         r"\) exited 1"):
        run_study(*declared(broken), [], execute=fake_pytest(broken, calls, fail=(2, 3)),
                  say=lambda line: None)
    failed = json.loads((broken / DESIGN_FILE).read_text())["rounds"][-1]
    assert failed == {"round": 1, "failed": ["native", "effnet_lite0", "effnet_lite0_random"],
                      "episodes_per_task": {"native": 4, "effnet_lite0": 4,
                                            "effnet_lite0_random": 4}, "exit_status": 1}
    resumed = len(calls)
    last = run_study(*declared(broken), [], execute=fake_pytest(broken, calls),
                     say=lambda line: None)
    # the round in flight goes on with the items it has not finished (the random twin's
    # extended cell resumes); effnet_lite0's are done
    rerun = calls[resumed]
    assert rerun[rerun.index("--rollouts") + 1:] == [
        "4", "-k", "pi05-spatial-native- or pi05-spatial-effnet_lite0_random-"]
    rounds = json.loads((broken / DESIGN_FILE).read_text())["rounds"]
    assert rounds[2] == {"round": 1, "episodes_per_task": {"native": 4, "effnet_lite0_random": 4}}
    final = json.loads((whole / DESIGN_FILE).read_text())["last"]
    assert last.summary == {k: v for k, v in final.items() if k not in ("stop", "spent_episodes")}
    with pytest.raises(SystemExit, match="declared with design"):  # another alpha: refused
        run_study(declared(broken)[0], SequentialDesign(0.05, 2000, 8), [],
                  execute=fake_pytest(broken, []))


def test_the_budget_and_the_init_states_stop_a_study(tmp_path):
    offline_study(tmp_path)
    last = run_study(*declared(tmp_path, budget=60), [], execute=fake_pytest(tmp_path, []),
                     say=lambda line: None)
    assert last.stop.startswith("budget") and last.spent <= 60
    study, design = declared(tmp_path / "other")
    offline_study(study.results)
    short = Study(study.results, study.items, "pi05", "spatial", TASKS, 2, 3, 2)
    last = run_study(short, design, [], execute=fake_pytest(study.results, []),
                     say=lambda line: None)
    assert last.stop.startswith("init states: round 1 needs 4 episodes per task")


def test_a_dry_run_prints_the_next_rounds_commands_and_writes_nothing(tmp_path, capsys):
    offline_study(tmp_path)
    assert main([str(tmp_path), "--items", ",".join(TRUTH), "--backbone", "pi05", "--suite",
                 "spatial", "--tasks", "0,1", "--per-task", "2", "--budget", "500",
                 "--dry-run", "--", "--grid", "g.toml"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == ("[sequential] after 0 round(s): native ~ effnet_lite0 ~ "
                      "effnet_lite0_random; 0 episodes rolled out of 500")
    (command,) = [line for line in out if "item" in line]  # one command for the round
    assert command.endswith("--rollouts 2 -k 'pi05-spatial-native- or pi05-spatial-effnet_lite0- "
                            "or pi05-spatial-effnet_lite0_random-'")
    assert not (tmp_path / DESIGN_FILE).exists()


GOOD = ["--items", ",".join(TRUTH), "--backbone", "pi05", "--suite", "spatial", "--tasks", "0,1",
        "--per-task", "2", "--budget", "500"]


def with_option(option: str, value: str) -> list[str]:
    args = list(GOOD)
    if option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    return args


@pytest.mark.parametrize("where, args, named", [
    ("missing", GOOD, "no such folder"),
    ("study", with_option("--items", "native,efnet"), "--items 'efnet'"),
    ("study", with_option("--items", "native"), "--items 'native'"),
    ("study", with_option("--items", "native,native"), "two or more distinct"),
    ("study", with_option("--backbone", "pi5"), "did you mean 'pi05'"),
    ("study", with_option("--tasks", "0,x"), "--tasks '0,x'"),
    ("study", with_option("--per-task", "0"), "--per-task: 0"),
    ("study", with_option("--budget", "-5"), "--budget: -5"),
    ("study", with_option("--alpha", "2"), "--alpha 2.0"),
    ("study", with_option("--max-per-task", "1"), "--max-per-task 1 is below --per-task 2"),
], ids=["no-folder", "unknown-item", "one-item", "same-item-twice", "unknown-backbone",
        "bad-tasks", "per-task-0", "negative-budget", "alpha-2", "max-below-per-task"])
def test_bad_arguments_stop_in_one_line_before_any_record_is_read(tmp_path, capsys, where, args,
                                                                   named):
    root = tmp_path / where
    if where == "study":
        offline_study(root)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    with pytest.raises(SystemExit) as stop:
        main([str(root), *args, "--", "--grid", "g.toml"])
    err = capsys.readouterr().err.strip()
    assert stop.value.code == 4 and named in err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written
