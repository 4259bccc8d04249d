"""The sequential study's runner (bench.analysis.sequential_study) without the simulator: a fake
`pytest` grows the selected cells' episodes from planted success rates, so the rounds, their
commands, the stops, the declaration and resuming after a failed command are checked."""

from __future__ import annotations

import json
import zlib

import pytest

from bench.analysis.sequential import SequentialDesign
from bench.analysis.sequential_study import (DESIGN_FILE, Study, cell_pattern, main,
                                             run_study)
from bench.grid.kinds import cell_id
from bench.results.store import ResultStore, load_results
from tests.factories import make_record

TRUTH = {"native": 0.95, "effnet_lite0": 0.5, "effnet_lite0_random": 0.05}
TASKS = (0, 1)


def offline_study(root) -> ResultStore:
    """Each item's two cells (releases 0 and 1, seed 0) as the offline study leaves them."""
    store = ResultStore(root)
    for item in TRUTH:
        kind, encoder = ("native", None) if item == "native" else ("graft", item)
        for release in (0, 1):
            store.write(make_record(kind=kind, backbone="pi05", encoder=encoder).replace(
                release=release, cell_id=cell_id(kind, "pi05", "spatial", encoder, 0, None,
                                                 release)))
    return store


def fake_pytest(root, calls: list, fail: tuple | None = None):
    """`execute(cmd)`: roll the -k-selected cells out to --rollouts N per task, success drawn
    from TRUTH per (item, release, task, episode); exit 1 at call `fail[0]` (after `fail[1]`
    of its cells are written: a kill mid-item)."""
    def execute(cmd: list[str]) -> int:
        calls.append(cmd)
        n, pattern = int(cmd[cmd.index("--rollouts") + 1]), cmd[cmd.index("-k") + 1]
        store = ResultStore(root)
        cells = [r for r in load_results(root).records if r.cell_id.startswith(pattern)]
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
                             "pi05-spatial-native-"] and calls[0][3:6] == ["bench", "--grid",
                                                                           "g.toml"]
    # every round asks for 2 more episodes per task of each item it runs; racing runs fewer
    rounds = json.loads((tmp_path / DESIGN_FILE).read_text())["rounds"]
    assert [r["round"] for r in rounds] == list(range(len(rounds)))
    assert all(set(r["episodes_per_task"].values()) == {2 * (r["round"] + 1)} for r in rounds)
    assert len(calls) < 3 * len(rounds)  # the random twin, resolved early, sat rounds out
    assert lines[-1] == "[sequential] stopped: resolved"
    stored = load_results(tmp_path).records
    assert last.spent == sum(len(r.run.rollouts["episodes"]) for r in stored)


def test_a_failed_command_stops_and_a_rerun_continues_to_the_same_study(tmp_path):
    whole, broken = tmp_path / "whole", tmp_path / "broken"
    for root in (whole, broken):
        offline_study(root)
    run_study(*declared(whole), [], execute=fake_pytest(whole, []), say=lambda line: None)
    calls = []
    with pytest.raises(SystemExit, match="effnet_lite0 exited 1"):  # killed after one cell
        run_study(*declared(broken), [], execute=fake_pytest(broken, calls, fail=(5, 1)),
                  say=lambda line: None)
    assert json.loads((broken / DESIGN_FILE).read_text())["rounds"][-1]["failed"] == "effnet_lite0"
    resumed = len(calls)
    last = run_study(*declared(broken), [], execute=fake_pytest(broken, calls),
                     say=lambda line: None)
    # the round in flight goes on with the items it has not finished: native's is done
    assert [c[-1] for c in calls[resumed:resumed + 2]] == [
        "pi05-spatial-effnet_lite0-", "pi05-spatial-effnet_lite0_random-"]
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
    commands = [line for line in out if "item" in line]
    assert len(commands) == 3 and all("--rollouts 2 -k pi05-spatial-" in c for c in commands)
    assert not (tmp_path / DESIGN_FILE).exists()
