"""Bad input to every entry point: `pytest bench`, `python -m bench.report`,
`bench.export`, `bench.offline_hub`, `bench.sim.demos` each stop before measuring or writing
anything, in one short screen naming the option (or variable), the value and the fix, with ONE
exit code for bad input: 4, pytest's usage error (a literal here, not the code's constant, which
could drift with its callers). The probe classes (docs/TESTING.md, "Bad-input probes"): number
and choice typos, empty lists, protocol ranges (one table, every entry),
the environment (cache, executor, baseline folder), a report over no records, and the rerun fix
bench.export prints. Every case runs in this process (no interpreter start): a fraction of a
second each.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

import backbones  # noqa: F401  (imported before pytester's sys.modules snapshot)
import encoders  # noqa: F401
from bench.grid.gridfile import GridFileError, parse_grid
from bench.grid.protocol import PROTOCOL_RANGES, GridFileInfo, Protocol, range_error
from tests.bench_inprocess import bench_run  # noqa: F401  (the fixture)
from tests.factories import make_failed, make_record, save_record

pytest_plugins = ["pytester"]


def assert_one_screen(out, *says: str) -> None:
    """Exit 4, no traceback or frames, at most 3 lines, no cell collected, each of `says`."""
    assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
    for text in says:
        assert text in out.screen, out.screen
    assert "Traceback" not in out.screen and "usage:" not in out.screen, out.screen
    assert not re.search(r"^\S+\.py:\d+: in ", out.screen, re.MULTILINE), out.screen
    lines = [line for line in out.screen.splitlines() if line.strip()]
    assert len(lines) <= 3 and lines[0].startswith("ERROR: "), out.screen
    assert "collected" not in out.screen


# --- pytest bench: options --------------------------------------------------------------------
# (arguments, what the screen must say): argparse's `type=` / `choices=` gave its usage block
# and no fix; an empty --robustness ran the default grid with robustness off.
OPTION_CASES = [
    (["--steps", "1e3"], "--steps 1e3: not a whole number; give e.g. --steps 1000"),
    (["--steps", "abc"], "--steps abc: not a whole number; give e.g. --steps 1000"),
    (["--rollouts", "2.5"], "--rollouts 2.5: not a whole number"),
    (["--sim-demo-noise", "lots"], "--sim-demo-noise lots: not a number"),
    (["--slurm-time", "ten"], "--slurm-time ten: not a whole number; give e.g. --slurm-time 240"),
    (["--feature-dtype", "fp8"], "--feature-dtype fp8: not one of fp16, bf16, float32"),
    (["--executor", "slrum"], "--executor slrum: not one of local, slurm, submitit-local; give "
     "e.g. --executor slurm"),
    (["--features", "cached"], "--features cached: not one of cache, loop"),
    (["--rollout-envs", "parallel"], "--rollout-envs parallel: not one of sync, async"),
    (["--robustness", ""], "--robustness '': empty (an unset variable?)"),
    (["--robustness", ",,,"], "--robustness ',,,': no item in the list"),
    (["--steps", "0"], "--steps: steps = 0 is out of range; give steps >= 1"),
    (["--steps", "-5"], "--steps: steps = -5 is out of range; give steps >= 1"),
    # Before: each of these started; the first ran out of memory building the batch order.
    (["--steps", "100000000000"], "--steps: steps = 100000000000 is out of range; give steps <= "
     "1000000 (500x the study's 2,000 steps, which run one after another)"),
    (["--controls", "tuned_encoder_1_8"], "--controls tuned_encoder_1_8: tuned_encoder_1_8 is "
     "compared with the short_graft[1_8] graft, a tier of the --screen ladder"),
    (["--screen", "--screen-keep", "ALL"], "--screen-keep ALL: keywords are lower case; give "
     "--screen-keep all"),
    (["--robustness", "ALL"], "--robustness ALL: ALL: keywords are lower case; give all"),
    (["--controls", "NONE"], "--controls NONE: keywords are lower case; give --controls none"),
    (["--controls", "natve"], "unknown control kind(s) ['natve'] (did you mean native?)"),
    (["--degrade-encoder", "dinov2:0.5"], "--degrade-encoder dinov2:0.5: 'dinov2' is not an "
     "encoder of this run (dinov2_s, pixels, blind), so nothing would be degraded; fix: "
     "--degrade-encoder dinov2_s:0.5"),
]


@pytest.mark.parametrize("args, says", OPTION_CASES, ids=[" ".join(a) for a, _ in OPTION_CASES])
def test_a_bad_option_value_is_one_line_with_the_fix(bench_run, args, says):
    assert_one_screen(bench_run(*args), says)


# --- pytest bench: grid files -------------------------------------------------------------------
GRID_CASES = [
    ("steps = 0", "steps = 0 is out of range; give steps >= 1"),
    ("[protocol]\nlr = -1.0", "[protocol]: lr = -1.0 is out of range; give lr > 0"),
    ("[protocol]\nbatch_size = 0", "batch_size = 0 is out of range; give batch_size >= 1"),
    ("[protocol]\nheldout_episodes_per_task = 0", "heldout_episodes_per_task = 0 is out of range"),
    ("[protocol]\neval_stride = 0", "eval_stride = 0 is out of range; give eval_stride >= 1"),
    ("encoders = []", "encoders = []: an empty list selects no cell; give e.g. encoders = "),
    ("seeds = []", "seeds = []: give a non-empty list"),
    ('robustness = "all"', "give a list of names, e.g. robustness = [\"brightness\""),
    ('robustness = ["ALL"]', "robustness: ALL: keywords are lower case; give all"),
    ("steps = 100000000000000000", "steps = 100000000000000000 is out of range; give steps <= "
     "1000000 (500x"),
    ("[protocol]\nlr = nan", "[protocol]: lr = nan is not a finite number; give lr > 0"),
    ("[protocol]\nlr = inf", "[protocol]: lr = inf is not a finite number; give lr > 0"),
    ("[protocol]\nheldout_episodes_per_task = 1000", "[protocol]: heldout_episodes_per_task = "
     "1000: the generated tiny suite 'spatial' has 16 episodes per task, and each task needs at "
     "least one left to train on; give heldout_episodes_per_task <= 15"),
    ("[protocol]\nbatch_size = 1000000000", "[protocol]: batch_size = 1000000000: the generated "
     "tiny suite 'spatial' has at most 2400 training frames"),
]


@pytest.mark.parametrize("text, says", GRID_CASES, ids=[t for t, _ in GRID_CASES])
def test_a_bad_grid_file_value_is_refused_at_start(bench_run, text, says):
    study = bench_run.path / "study.toml"
    study.write_text(text + "\n")
    assert_one_screen(bench_run("--grid", str(study)), str(study), says)


def test_every_numeric_protocol_field_has_a_range():
    """A numeric field added to Protocol without its entry in PROTOCOL_RANGES fails here."""
    numeric = {f.name for f in dataclasses.fields(Protocol)
               if type(f.default) in (int, float)}
    assert numeric - set(PROTOCOL_RANGES) == set(), "add the field's range to PROTOCOL_RANGES"
    assert set(PROTOCOL_RANGES) - numeric == set(), "a range for a field Protocol lacks"
    for name, allowed in PROTOCOL_RANGES.items():
        assert getattr(Protocol(), name) in allowed, f"the default {name} is out of its range"


@pytest.mark.parametrize("name", sorted(PROTOCOL_RANGES))
def test_a_value_outside_each_range_is_refused_from_a_grid_file_with_the_one_message(name):
    allowed = PROTOCOL_RANGES[name]
    below = allowed.low if allowed.low_open else allowed.low - 1
    if isinstance(Protocol().__getattribute__(name), float):
        below = float(below)
    info = GridFileInfo("study.toml", "0" * 64, "")
    with pytest.raises(GridFileError) as err:
        parse_grid({"protocol": {name: below}}, info)
    assert str(err.value) == range_error(name, below, "study.toml [protocol]")
    if allowed.high is not None:
        with pytest.raises(GridFileError, match="out of range"):
            parse_grid({"protocol": {name: allowed.high + 1}}, info)


# --- pytest bench: the environment, before any cell ---------------------------------------------
@pytest.mark.parametrize("value, says", [
    ("{tmp}/cache-file", "GRAFTBENCH_CACHE={tmp}/cache-file: a file, not a folder; fix:"),
    ("{tmp}/cache-file/sub", "GRAFTBENCH_CACHE={tmp}/cache-file/sub: {tmp}/cache-file is a file"),
    ("", "GRAFTBENCH_CACHE='': empty (an unset variable?)"),  # Path(""): the current folder
], ids=["a-file", "under-a-file", "empty"])
def test_a_bad_cache_variable_is_refused_at_start(bench_run, monkeypatch, value, says):
    """Before: start-up passed, then every cell failed with a 73-line FileExistsError."""
    (bench_run.path / "cache-file").write_text("")
    monkeypatch.setenv("GRAFTBENCH_CACHE", value.format(tmp=bench_run.path))
    assert_one_screen(bench_run(), says.format(tmp=bench_run.path))


def test_a_report_path_under_a_file_says_so(bench_run):
    """Before: `--report: FILE is not writable (File exists)`."""
    (bench_run.path / "f").write_text("")
    assert_one_screen(bench_run("--report", str(bench_run.path / "f" / "R.md")),
                      f"--report: {bench_run.path / 'f'}: a file, not a folder")


def test_a_baseline_with_no_finished_record_is_not_saved_over_the_old_one(tmp_path):
    """An empty snapshot would replace a baseline with less than it held."""
    from bench.regression.run import BaselineOptions, BaselineRun

    (tmp_path / "ci.json").write_text("the old baseline")
    run = BaselineRun(BaselineOptions(dir=tmp_path, save_name="ci"), "0" * 12)
    assert run.finish(["smolvla-spatial-pixels-seed0"], {}) == []
    assert (tmp_path / "ci.json").read_text() == "the old baseline"
    assert run.saved is None and "baseline ci NOT saved: none of the 1 selected" in run.not_saved


def test_slurm_without_slurm_is_refused_at_start(bench_run, monkeypatch):
    """Before: every cell failed with a 75-line submitit traceback."""
    monkeypatch.setattr("shutil.which", lambda name: None)
    assert_one_screen(bench_run("--executor", "slurm"), "--executor slurm: no Slurm here",
                      "--executor local")


def test_a_baseline_dir_naming_a_file_is_refused_at_start(bench_run):
    """Before: found only after the whole run (exit 3)."""
    target = bench_run.path / "baselines.txt"
    target.write_text("")
    assert_one_screen(bench_run("--baseline-dir", str(target), "--save-baseline", "ci"),
                      f"--baseline-dir {target}: a file, not a folder; fix:")


# --- python -m bench.report ---------------------------------------------------------------------
def report(argv, capsys) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of `python -m bench.report ARGV`, in this process."""
    from bench.report.cli import main

    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def old_report(folder: Path) -> dict:
    """A report a past run wrote: its three files, by name, with their bytes."""
    files = {"REPORT.md": b"# the old report\n", "REPORT_cells.csv": b"cell_id\nx\n",
             "REPORT_summary.json": b"{}\n"}
    for name, blob in files.items():
        (folder / name).write_bytes(blob)
    return files


@pytest.mark.parametrize("layout", ["empty", "above", "unreadable"])
def test_a_report_over_no_records_refuses_and_leaves_every_file(tmp_path, capsys, layout):
    """Before: exit 0, "wrote", and REPORT.md, its CSV and JSON overwritten with "No finished
    cells"; `.graftbench/results` (one level above a results dir) is the usual slip."""
    files = old_report(tmp_path)
    if layout == "above":
        save_record(tmp_path / "tiny", make_record())
    if layout == "unreadable":  # before: a failure file with a number for its id was a cell
        for folder, text in (("cells", "{not json"), ("failed", '{"cell_id": 5}')):
            (tmp_path / folder).mkdir()
            (tmp_path / folder / "a.json").write_text(text)
    code, out, err = report([tmp_path], capsys)
    assert code == 4 and out == "" and err.count("\n") == 1, err
    assert f"RESULTS_DIR {tmp_path}: no" in err and "nothing written" in err
    if layout == "above":
        assert f"results dirs below it: {tmp_path / 'tiny'}" in err
    if layout == "unreadable":
        assert "2 unreadable file(s) skipped: cells/a.json" in err and "failed/a.json" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == files


@pytest.mark.parametrize("args, says", [
    (["--resamples", "0"], "argument --resamples: 0: give a whole number >= 2"),
    (["--resamples", "-5"], "argument --resamples: -5: give a whole number >= 2"),
    (["--report", "{dir}"], "--report {dir}: a folder; --report names the report's file"),
    (["--report", "{dir}/x/REPORT.md"], "{dir}/x: a file, not a folder; give a path in a folder"),
    # a folder not made yet, typed as one: it was written as a file named "new"
    (["--report", "{dir}/new/"], "--report {dir}/new/: a folder; --report names the report's"),
], ids=["resamples-0", "resamples-negative", "report-a-folder", "report-under-a-file",
        "report-a-new-folder"])
def test_a_bad_report_option_is_one_line(tmp_path, capsys, args, says):
    """Before: a 33-line scipy traceback; an IsADirectoryError traceback."""
    save_record(tmp_path, make_record())
    (tmp_path / "x").write_text("")  # a file where a folder would go
    args = [a.format(dir=tmp_path) for a in args]
    code, out, err = report([tmp_path, "--no-plots", *args], capsys)
    assert code == 4 and err.count("\n") == 1 and says.format(dir=tmp_path) in err, err
    assert not (tmp_path / "REPORT.md").exists() and not (tmp_path / "new").exists()


def test_a_file_as_the_results_dir_is_called_a_file(tmp_path, capsys):
    (tmp_path / "REPORT.md").write_text("")
    code, _, err = report([tmp_path / "REPORT.md"], capsys)
    assert code == 4 and "a file, not a folder" in err, err


def test_a_report_that_skipped_files_says_how_many_in_the_terminal(tmp_path, capsys):
    save_record(tmp_path, make_record())
    (tmp_path / "cells" / "junk.json").write_text('{"cell_id": 5}')
    code, out, err = report([tmp_path, "--no-plots", "--resamples", "20", "--skip-unreadable"],
                            capsys)
    assert code == 0 and out.startswith(f"wrote {tmp_path / 'REPORT.md'} (1 finished"), out
    assert "skipped 1 unreadable file(s), not in the report: cells/junk.json" in err, err


# --- python -m bench.export, bench.offline_hub, bench.sim.demos: one exit code ---------------------
def run_main(main, argv, capsys) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as e:
        code = e.code
    return code, capsys.readouterr().err


def _export_main(argv):
    from bench.export.__main__ import main

    return main(argv)


def _hubworld_main(argv):
    from bench.offline_hub import main

    return main(argv)


def _demos_main(argv):
    from bench.sim.demos import main

    return main(argv)


ENTRY_CASES = [
    (_export_main, ["--list"], "the following arguments are required: --results-dir"),
    (_export_main, ["x", "--results-dir", "{tmp}"], "--out OUT is required"),
    (_export_main, ["x", "--results-dir", "{tmp}/none", "--out", "{tmp}/o"], "no results at"),
    (_hubworld_main, [], "the following arguments are required: DIR"),
    (_hubworld_main, ["{tmp}/f"], "DIR {tmp}/f: a file, not a folder"),
    (_hubworld_main, ["{tmp}/f/world"], "{tmp}/f is a file"),
    (_hubworld_main, ["{tmp}"], "holds other files (f), not a hub world"),
    (_demos_main, ["--tasks", "0,x"], "--tasks '0,x': not a comma list of LIBERO task ids"),
    (_demos_main, ["--tasks", "0,4"], "--tasks 0,4: the scripted expert cannot solve"),
    (_demos_main, ["--episodes", "0"], "argument --episodes: 0: give a whole number >= 1"),
    (_demos_main, ["--episodes", "5", "--max-attempts", "2"], "--episodes 5 --max-attempts 2:"),
    (_demos_main, ["--root", "{tmp}/f"], "--root {tmp}/f: a file, not a folder"),
]


@pytest.mark.parametrize("main, argv, says", ENTRY_CASES,
                         ids=[f"{m.__name__[1:-5]} {' '.join(a)}" for m, a, _ in ENTRY_CASES])
def test_every_entry_point_answers_bad_input_with_exit_4_in_one_line(tmp_path, capsys, main,
                                                                    argv, says):
    """Before: bench.export and argparse exited 2, hubworld 1, pytest bench 4."""
    (tmp_path / "f").write_text("")
    code, err = run_main(main, [a.format(tmp=tmp_path) for a in argv], capsys)
    assert code == 4 and err.count("\n") == 1, err
    assert says.format(tmp=tmp_path) in err and "usage:" not in err, err


def test_demos_without_the_simulator_stop_before_any_env(capsys, monkeypatch):
    import bench.sim.env

    monkeypatch.setattr(bench.sim.env, "libero_available", lambda: False)
    code, err = run_main(_demos_main, [], capsys)
    assert code == 4 and "the LIBERO simulator (the libero extra) is not installed; " \
        "fix: " in err, err


def test_the_export_rerun_fix_is_the_command_that_measured_the_cell(tmp_path, capsys):
    """Before: `pytest bench -k CELL --results-dir DIR`, which drops the run's --grid / --profile
    / --encoders and so selects nothing for a cell outside the default grid (exit 5)."""
    study = {"path": "studies/mine.toml", "sha256": "0" * 64, "text": "steps = 60\n"}
    save_record(tmp_path, make_record(encoder="timm:resnet18", seed=3, grid_file=study))
    failed = make_failed(backbone="pi05", encoder="timm:resnet18", seed=3)
    save_record(tmp_path, failed)
    code, err = run_main(_export_main, [failed.cell_id, "--results-dir", str(tmp_path),
                                        "--out", str(tmp_path / "out")], capsys)
    assert code == 4 and err.count("\n") == 1, err
    assert (f"run it again (pytest bench --grid studies/mine.toml --profile tiny --backbones pi05 "
            f"--suites spatial --seeds 3 --encoders timm:resnet18 --controls none -k "
            f"{failed.cell_id} --results-dir {tmp_path})") in err, err


def test_a_k_expression_that_selects_no_cell_names_ids_to_pick_from(bench_run):
    # pytest's own answer was "no tests collected" (exit 5), with README writing screen ids as
    # `timm:convnext_atto` where the real ids say `timm_`.
    out = bench_run("-k", "nomatch")
    assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
    assert "-k 'nomatch' selects none of the 14 cases" in out.screen, out.screen
    assert "test_graft[pi05-spatial-" in out.screen or "test_control[pi05-spatial-" in out.screen
    results = bench_run.path / "results"
    assert "Traceback" not in out.screen and not (results / "grid.json").exists()
    assert not any((results / "cells").iterdir())


@pytest.mark.parametrize("name", sorted(PROTOCOL_RANGES))
def test_nan_and_infinity_are_outside_every_range(name):
    """Before: NaN compares false with every bound, so `lr = nan` passed start-up."""
    for value in (float("nan"), float("inf"), float("-inf")):
        assert "is not a finite number" in range_error(name, value, "study.toml [protocol]")


def test_a_file_given_as_a_policy_folder_is_called_a_file(bench_run):
    """Before: "no such folder", for a file that exists."""
    (bench_run.path / "model.safetensors").write_text("")
    given = f"mine={bench_run.path / 'model.safetensors'}"
    assert_one_screen(bench_run("--policy", given), f"--policy {given}: a file, not a folder")


def test_a_paper_preflight_stop_leaves_no_folder_behind(bench_run):
    """Before: the stop left empty results/cells/ and results/failed/."""
    out = bench_run("--profile", "paper", "--backbones", "smolvla", "--suites", "spatial",
                    "--encoders", "dinov2_s", "--seeds", "0", "--controls", "none")
    assert out.ret == pytest.ExitCode.USAGE_ERROR and "missing" in out.screen, out.screen
    assert not (bench_run.path / "results").exists()


def test_a_tier_twin_without_the_screen_and_a_degraded_stranger_are_refused():
    """The guards behind the `--controls tuned_encoder_1_8` and `--degrade-encoder` rows, called
    directly (broken, those rows would measure the grid instead of refusing)."""
    from bench.grid.protocol import TINY
    from bench.regression.run import BaselineOptions, BaselineRun
    from bench.startup import check_references

    tuned = dataclasses.replace(TINY, controls=("tuned_encoder_1_8",))
    with pytest.raises(pytest.UsageError, match="short_graft.1_8. graft, a tier of the --screen"):
        check_references(tuned, screen=False)
    check_references(tuned, screen=True)
    with pytest.raises(pytest.UsageError, match="'dinov2' is not an encoder of this run"):
        BaselineRun(BaselineOptions(degrade=("dinov2", 0.5)), "0" * 12, TINY)
