"""The start-up check: each bad option, name or user path of `pytest bench` is ONE
UsageError screen (exit 4, no frames, no cell run), checked at pytest_configure, before
collection; duplicates are folded and said. And every fetch command the paper preflight prints
fetches what it says, as the pinned `hf` CLI's own parser reads it.

The bad inputs run `pytest bench` in this process (pytester): each stops at configure, so a
run costs well under a second, where a subprocess costs ~10 s here.
"""

from __future__ import annotations

import fnmatch
import os
import re
import shlex
import warnings
from pathlib import Path

import pytest

# Imported before pytester's sys.modules snapshot: the in-process runs reuse them (re-importing
# torchvision ops would fail) and pay no import time.
import backbones  # noqa: F401
import bench.screen.measure  # noqa: F401  (--screen: the screen's modules, torch's too)
import bench.resources.user_policies  # noqa: F401
import bench.sim.env  # noqa: F401  (its libero_available is replaced by tests below)
import bench.suites.user  # noqa: F401
import encoders  # noqa: F401
from ondisk.paths import REPO_ROOT
from tests.bench_inprocess import ONE_PROCESS

pytest_plugins = ["pytester"]

NO_CELLS = ["--backbones", "pi05", "--suites", "spatial", "--encoders", "pixels", "--controls",
            "native", "--steps", "2"]


@pytest.fixture
def bench_run(pytester):
    """`pytest bench ARGS` in this process, with a private results dir and report."""
    results = pytester.path / "results"

    def run(*args: str):
        out = pytester.runpytest_inprocess(
            str(REPO_ROOT / "bench"), "-p", "no:cacheprovider", *ONE_PROCESS, "--results-dir",
            str(results),
            "--report", str(pytester.path / "REPORT.md"), *args)
        out.screen = "\n".join(out.outlines + out.errlines)
        out.records = sorted(results.glob("cells/*.json"))
        return out

    run.path = pytester.path
    return run


# (arguments, what the screen must name: the option and the value, what it must say)
BAD_INPUTS = [
    (["--encoders", "timm:not_a_model_xyz"], "--encoders timm:not_a_model_xyz",
     "unknown timm model 'not_a_model_xyz'"),
    (["--encoders", "nosuchpkg.mod:make"], "--encoders nosuchpkg.mod:make",
     "no module 'nosuchpkg.mod' to import"),
    (["--encoders", "pixels,dinov3"], "--encoders pixels,dinov3", "unknown encoder 'dinov3'"),
    (["--suites", "nope"], "--suites nope", "valid suites: spatial, object"),
    (["--backbones", "nope"], "--backbones nope", "valid backbones: smolvla, pi05"),
    (["--controls", "nope"], "--controls nope", "valid: native, native_wrapped"),
    (["--seeds", "0,x"], "--seeds 0,x", "not a non-negative integer"),
    (["--steps", "0"], "--steps: steps = 0", "give steps >= 1"),
    # An empty list is not the default grid (a script's unset variable would launch a study).
    (["--encoders", ""], "--encoders ''", "empty (an unset variable?); give a value (e.g. "
     "--encoders dinov2_s,siglip), or leave --encoders out for the default"),
    (["--encoders", ","], "--encoders ','", "no item in the list; give a comma list"),
    (["--backbones", ""], "--backbones ''", "empty (an unset variable?)"),
    (["--backbones", " , "], "--backbones ' , '", "no item in the list"),
    (["--suites", ""], "--suites ''", "empty (an unset variable?)"),
    (["--seeds", ""], "--seeds ''", "empty (an unset variable?)"),
    (["--seeds", ",,"], "--seeds ',,'", "no item in the list"),
    (["--controls", ""], "--controls ''", "empty (an unset variable?)"),
    (["--controls", ","], "--controls ','", "no item in the list"),
    (["--profile", ""], "--profile ''", "empty (an unset variable?); give a value"),
    (["--results-dir", ""], "--results-dir ''", "empty"),
    (["--report", ""], "--report ''", "empty"),
    (["--grid", " "], "--grid ' '", "empty"),
    (["--camera-map", ""], "--camera-map ''", "empty"),
    (["--profile", "sim", "--sim-tasks", ","], "--sim-tasks ','", "no item in the list"),
    (["--profile", "nope"], "unknown profile 'nope'", "(--profile NAME)"),
    (["--rollouts", "-1"], "--rollouts -1", ">= 0"),
    (["--rollout-batch", "0"], "--rollout-batch 0", "rolled out at once >= 1"),
    (["--rollout-batch", "4"], "--rollout-batch 4", "fix: add --rollouts N"),
    (["--rollout-workers", "0"], "--rollout-workers 0", "worker processes >= 1"),
    (["--rollout-workers", "2"], "--rollout-workers 2", "fix: add --rollouts N"),
    (["--profile", "sim", "--sim-tasks", "0,4"], "--sim-tasks 0,4",
     "the scripted expert cannot solve LIBERO-spatial task 4 (measured 0/5"),
    (["--profile", "sim", "--sim-tasks", "0,x"], "--sim-tasks 0,x", "give e.g. --sim-tasks 0,1,2"),
    (["--sim-demos", "5"], "--sim-demos 5", "has no simulated suites; use --profile sim"),
    (["--profile", "sim", "--sim-demo-noise", "2"], "--sim-demo-noise 2.0", "0 to 1"),
    (["--profile", "sim", "--sim-demo-speed", "0"], "--sim-demo-speed 0.0", "0 < S <= 1"),
    (["--sim-demo-speed", "0.5"], "--sim-demo-speed 0.5", "has no simulated suites"),
    (["--profile", "sim", "--sim-demos", "20", "--rollouts", "30"], "--rollouts 30",
     "give --rollouts <= 26"),
    (["--slurm-time", "0"], "--slurm-time 0", ">= 1"),
    (["--policy", "mine=/nonexistent/policy"], "--policy mine=/nonexistent/policy",
     "no such folder; fix: give the folder save_pretrained wrote"),
    (["--policy", "mine=not//a repo"], "--policy mine=not//a repo", "no such folder"),
    (["--policy", "mine=nobody/no_such_policy"], "--policy mine=nobody/no_such_policy",
     "no LeRobot checkpoint there"),
    (["--policy", "smolvla=/tmp"], "--policy smolvla", "the name of a built-in one"),
    (["--dataset", "mine=/nonexistent/data"], "--dataset mine=/nonexistent/data",
     "no LeRobotDataset there"),
    (["--grid", "/nonexistent/study.toml"], "--grid /nonexistent/study.toml", "no such file"),
    (["--camera-map", "front=top"], "--camera-map front=top", "add --policy NAME=FOLDER"),
    (["--camera-map", "front"], "--camera-map 'front'", "POLICY_CAMERA=DATASET_CAMERA"),
    (["--screen", "--screen-keep", "0"], "--screen-keep 0", "give a whole number >= 1, or all"),
    (["--screen", "--screen-keep", "-2"], "--screen-keep -2", "give a whole number >= 1, or all"),
    (["--screen", "--screen-keep", "2.5"], "--screen-keep 2.5", "give a whole number >= 1, or all"),
    (["--screen", "--screen-by", "shortest"], "--screen-by shortest",
     "choose one of logme, ridge, knn, entropy, param_count, flops, resolution, short"),
    (["--screen", "--screen-by", "short", "--executor", "submitit-local"],
     "--screen-by short with --executor submitit-local", "fix: --executor local"),
    (["--screen-keep", "2"], "--screen-keep 2", "--screen is not given; fix: add --screen"),
    (["--screen-by", "ridge"], "--screen-by ridge", "--screen is not given; fix: add --screen"),
    (["--screen-calibration", "/tmp"], "--screen-calibration /tmp",
     "--screen is not given; fix: add --screen"),
    (["--screen", "--screen-calibration", "/nonexistent/calib", "--collect-only"],
     "--screen-calibration /nonexistent/calib", "no such results dir; fix: name the --results-dir "
     "of a `pytest bench --screen --screen-keep all` run"),
]


@pytest.mark.parametrize("args, names, says", BAD_INPUTS, ids=[" ".join(a) for a, _, _ in BAD_INPUTS])
def test_a_bad_input_is_one_usage_error_screen_before_collection(bench_run, args, names, says):
    out = bench_run(*args)
    assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
    assert names in out.screen and says in out.screen, out.screen
    assert "Traceback" not in out.screen and "pluggy" not in out.screen, out.screen
    assert not re.search(r"^\S+\.py:\d+: in ", out.screen, re.MULTILINE), out.screen  # frames
    lines = [line for line in out.screen.splitlines() if line.strip()]
    assert len(lines) <= 3 and lines[0].startswith("ERROR: "), out.screen
    assert "collected" not in out.screen and out.records == []


def test_a_calibration_study_without_screens_or_grafts_is_refused(bench_run):
    """--screen-calibration names a folder that holds no calibration study: no screen at all, or
    screens without a graft of a screened encoder (the screens of a `-k test_screen` run).
    --collect-only: were the check gone, these runs would stop after collecting, not run cells."""
    from bench.screen.records import ScreenConditions, ScreenScores, new_screen_record
    from bench.results.store import ResultStore

    store = ResultStore(bench_run.path / "calib")
    out = bench_run("--screen", "--screen-calibration", str(store.root), "--collect-only")
    assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
    assert out.screen.splitlines()[0] == (
        f"ERROR: --screen-calibration {store.root}: no screen record there (screens/*.json: it "
        "was not a --screen run); fix: name the --results-dir of a `pytest bench --screen "
        "--screen-keep all` run, or drop the option")
    screen = ScreenScores("pixels", "smolvla", "spatial")
    screen.proxies = {"logme": {"gain": 0.1}}
    store.write_screen(new_screen_record(screen, ScreenConditions("h", "f", "fp16"), 1.0))
    out = bench_run("--screen", "--screen-calibration", str(store.root), "--collect-only")
    assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
    assert ("1 screen(s) but no graft of a screened encoder there (cells/*.json): no agreement "
            "to quote; fix:") in out.screen.splitlines()[0]
    assert out.records == []


def test_rollouts_without_the_libero_extra_say_how_to_install_it(monkeypatch):
    """The session's start-up check (bench.session calls it before collection; that it runs there
    is test_grid_plugin's --rollouts case): one line, the option, the value and the fix."""
    from bench.grid.protocol import get_profile
    from bench.startup import check_rollouts_possible

    import importlib

    # The module object the check imports (an in-process pytester run may have re-imported it).
    monkeypatch.setattr(importlib.import_module("bench.sim.env"), "libero_available", lambda: False)
    with pytest.raises(pytest.UsageError) as error:
        check_rollouts_possible(get_profile("sim"), 2)
    assert str(error.value) == ("--rollouts 2: the LIBERO simulator (the libero extra) is not "
                                "installed; fix: install the extra: bash scripts/install_libero.sh")


def _without_libero(monkeypatch, tmp_path) -> None:
    """The libero extra missing and an empty cache (no simulated suite generated yet)."""
    import importlib

    # The module object the checks import (imported above, before pytester's snapshot).
    monkeypatch.setattr(importlib.import_module("bench.sim.env"), "libero_available", lambda: False)
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "empty-cache"))


def test_the_sim_profile_without_the_libero_extra_is_one_line_at_start(bench_run, monkeypatch,
                                                                       tmp_path):
    """Were the check gone, each of the grid's cells would start and fail on its own (exit 1,
    a failure record each)."""
    _without_libero(monkeypatch, tmp_path)
    out = bench_run("--profile", "sim", "--encoders", "pixels", "--controls", "none")
    assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
    lines = [line for line in out.screen.splitlines() if line.strip()]
    assert lines[0].startswith("ERROR: --profile sim: the simulated suite 'spatial' is not "
                               "generated yet ("), out.screen
    assert lines[0].endswith("generating it needs the LIBERO simulator (the libero extra), which "
                             "is not installed; fix: install the extra: bash "
                             "scripts/install_libero.sh, or use --profile tiny (generated suites)")
    assert len(lines) <= 3 and "collected" not in out.screen and out.records == [], out.screen


def test_a_rollout_count_too_large_is_named_without_the_extra_too(bench_run, monkeypatch,
                                                                 tmp_path):
    """The value's own bound comes before the machine's: the line BAD_INPUTS reads on a machine
    with the extra is the line a machine without it shows."""
    _without_libero(monkeypatch, tmp_path)
    out = bench_run("--profile", "sim", "--sim-demos", "20", "--rollouts", "30")
    assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
    assert out.screen.splitlines()[0] == (
        "ERROR: --rollouts 30: with 20 demonstrations per task (init states 0..23) rollouts "
        "would reuse a demonstration's init state; give --rollouts <= 26"), out.screen


def test_a_report_naming_a_folder_is_refused_at_start(bench_run):
    """Before: every cell measured, then "REPORT.md not written: IsADirectoryError", exit 0."""
    folder = bench_run.path / "reports"
    folder.mkdir()
    for given in (str(folder), str(bench_run.path / "new-folder") + "/"):
        out = bench_run(*NO_CELLS, "--report", given)
        assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
        assert out.screen.splitlines()[0] == (
            f"ERROR: --report {given}: a folder; --report names the report's file (its plots, "
            f"CSV and JSON go beside it), e.g. --report {Path(given) / 'REPORT.md'}"), out.screen
        assert "collected" not in out.screen and out.records == [], out.screen


def test_a_report_that_could_not_be_written_is_said_not_left_as_it_was(tmp_path):
    """The summary after a report that failed to write (were --report's start-up check
    bypassed, or the disk full): it was "left as it was (this run finished no new cell)"."""
    from bench.cell.outcome import MEASURED
    from bench.summary import summary_lines

    lines = summary_lines("tiny", "h", {"pi05-spatial-pixels-seed0": MEASURED}, 1, tmp_path,
                          tmp_path, False, "IsADirectoryError: [Errno 21] Is a directory")
    assert lines[3] == (f"report: NOT WRITTEN to {tmp_path} (IsADirectoryError: [Errno 21] Is a "
                        "directory)"), lines


def test_the_check_runs_under_collect_only_and_xdist(bench_run):
    for extra in (["--collect-only"], ["-n", "2"]):
        out = bench_run("--suites", "nope", *extra)
        assert out.ret == pytest.ExitCode.USAGE_ERROR, out.screen
        assert out.screen.splitlines()[0].startswith("ERROR: --suites nope: unknown suite")


def test_a_bad_results_dir_and_report_are_refused_at_start(bench_run):
    taken = bench_run.path / "a_file"
    taken.write_text("")
    out = bench_run(*NO_CELLS, "--results-dir", str(taken / "results"))
    assert out.ret == pytest.ExitCode.USAGE_ERROR and "--results-dir" in out.screen, out.screen
    out = bench_run(*NO_CELLS, "--report", str(taken / "REPORT.md"))
    assert out.ret == pytest.ExitCode.USAGE_ERROR and "--report" in out.screen, out.screen


def test_seeds_and_encoders_listed_twice_are_folded_and_said(bench_run):
    out = bench_run("--backbones", "pi05", "--suites", "spatial", "--encoders",
                    "pixels,blind,pixels", "--seeds", "0,0", "--controls", "native,native",
                    "--collect-only", "-q")
    assert out.ret == pytest.ExitCode.OK, out.screen
    assert ("[graftbench] --seeds 0,0: 0 listed twice, folded: each cell runs once (seeds 0)"
            in out.outlines)
    assert ("[graftbench] --encoders pixels,blind,pixels: pixels listed twice, folded: each cell "
            "runs once (encoders pixels,blind)") in out.outlines
    assert any(line.startswith("[graftbench] --controls native,native:") for line in out.outlines)
    ids = [line for line in out.outlines if "::test_" in line]
    assert ids == ["bench/test_grid.py::test_graft[pi05-spatial-pixels-seed0]",
                   "bench/test_grid.py::test_graft[pi05-spatial-blind-seed0]",
                   "bench/test_grid.py::test_control[pi05-spatial-native-seed0]"]


# --- the fetch commands the preflight prints, read by the pinned hf CLI -----------------------

def hf_fetch(command: str, monkeypatch) -> dict:
    """What `command` (`hf download ...`) would fetch: the pinned huggingface_hub CLI parses it
    and runs its own download command, with its two fetchers replaced by recorders (no network).
    {"repo_id", "repo_type", "revision", "filename" (one file) or "allow_patterns"}, "warnings"."""
    from huggingface_hub.cli import download as cli_download
    from huggingface_hub.cli import hf

    calls = []
    for fetcher in ("snapshot_download", "hf_hub_download"):
        monkeypatch.setattr(cli_download, fetcher, lambda **kw: calls.append(kw) or "")
    words = shlex.split(command)
    assert words[:2] == ["hf", "download"], command
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        hf.app(args=words[1:], prog_name="hf", standalone_mode=False)
    (call,) = calls
    fetched = {k: call.get(k) for k in ("repo_id", "repo_type", "revision", "filename",
                                        "allow_patterns")}
    return {**fetched, "warnings": [str(w.message) for w in caught]}


def test_the_old_pattern_list_is_what_the_cli_misreads(monkeypatch):
    """The parser check sees the bug this module guards: a pattern after the first --include
    value is a file name, and file names override every pattern: one file, literally `*.txt`."""
    fetched = hf_fetch('hf download o/r --include "*.json" "*.txt"', monkeypatch)
    assert (fetched["filename"], fetched["allow_patterns"]) == ("*.txt", None)
    assert "Ignoring `--include` since filenames have been explicitly set." in fetched["warnings"]


@pytest.fixture
def empty_caches(monkeypatch, tmp_path):
    """The Hugging Face and LeRobot caches empty: every artifact missing, every fix printed."""
    import lerobot.utils.constants as lerobot_constants
    from huggingface_hub import constants as hub_constants

    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr(lerobot_constants, "HF_LEROBOT_HOME", tmp_path / "lerobot")
    monkeypatch.delenv("GRAFTBENCH_LIBERO_ROOT", raising=False)


def _expected_patterns(artifact) -> list[str] | None:
    """The include patterns the artifact's owner declares (None: the whole repo)."""
    from backbones.paligemma_load import TOKENIZER_INCLUDE
    from backbones.smolvla_load import VLM_INCLUDE

    return {"vlm config": list(VLM_INCLUDE), "tokenizer": list(TOKENIZER_INCLUDE)}.get(artifact.kind)


def test_every_fetch_command_the_preflight_prints_fetches_what_it_says(empty_caches, monkeypatch):
    from backbones import BACKBONES
    from bench.preflight import grid_artifacts, render
    from bench.suites.libero import LIBERO_REPO_IDS
    from encoders import get_spec, list_encoders
    from encoders.timm_encoders import hub_weights

    from encoders.registry import own_weights

    # encoders whose weights come from the hub cache (the real ones' wheels are installed)
    hub_encoders = [e for e in list_encoders() if own_weights(e) is None]
    on_hub = [name for name, entry in BACKBONES.items() if entry.on_hub]  # not the tiny sizes
    artifacts = grid_artifacts(on_hub, hub_encoders, LIBERO_REPO_IDS)
    kinds = {a.kind for a in artifacts}
    assert kinds == {"policy", "vlm config", "tokenizer", "encoder weights", "dataset"}, kinds
    assert not any(a.present for a in artifacts)
    printed = [line.strip() for line in render(artifacts).splitlines()
               if line.strip().startswith("hf download")]
    assert printed == [a.fix for a in artifacts]  # one command per artifact, as built
    for artifact in artifacts:
        fetched = hf_fetch(artifact.fix, monkeypatch)
        assert fetched["warnings"] == [], (artifact.fix, fetched)
        assert (fetched["repo_id"], fetched["revision"]) == (artifact.repo_id, artifact.revision)
        assert fetched["repo_type"] == ("dataset" if artifact.kind == "dataset" else "model")
        if artifact.kind == "encoder weights":
            spec = get_spec(artifact.needed_by.removeprefix("encoder ").split(", ")[0])
            assert fetched["filename"] == hub_weights(spec.timm_name)[2][0], artifact.fix
            continue
        assert fetched["filename"] is None
        assert fetched["allow_patterns"] == _expected_patterns(artifact), artifact.fix
        # The files the preflight looks for are among those the command fetches.
        looked_for = artifact.where.rsplit(": ", 1)[1].split(", ") if artifact.kind != "dataset" \
            else ["meta/info.json"]
        patterns = fetched["allow_patterns"] or ["*"]
        for name in looked_for:
            assert any(fnmatch.fnmatch(name, p) for p in patterns), (artifact.fix, name)


def test_the_readme_fetch_commands_parse_without_warnings(monkeypatch):
    readme = (REPO_ROOT / "README.md").read_text()
    commands = [line.strip() for line in readme.splitlines()
                if line.strip().startswith("hf download ")]
    assert len(commands) >= 10
    for command in commands:
        assert hf_fetch(command, monkeypatch)["warnings"] == [], command


def test_download_command_takes_files_or_patterns_not_both():
    from ondisk.hubcache import download_command

    assert download_command("o/r", "abc", include=("*.json", "*.txt")) == (
        'hf download o/r --revision abc --include "*.json" --include "*.txt"')
    with pytest.raises(ValueError, match="not both"):
        download_command("o/r", include=("*.json",), files=("config.json",))


def test_the_plugin_loads_without_torch_or_lerobot():
    """A bad option is refused before the heavy imports: loading the pytest plugin (options,
    grid files, the session) imports neither torch nor LeRobot (~3.5 s on these cores)."""
    import subprocess
    import sys

    code = "import sys, bench.plugin; print(sorted({'torch', 'lerobot'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_names_are_checked_and_a_grid_collected_without_lerobot(tmp_path):
    """The start-up check and collection (what a bad option's screen and an xdist controller run)
    validate encoder names with torch and timm alone: the shared encoder lives in `graftcore`,
    not in the LeRobot plugin package whose import registers its configs (a usage error took
    8.4 s on these cores with it, 4.5 s without)."""
    import subprocess
    import sys

    out = ["--results-dir", str(tmp_path / "results"), "--report", str(tmp_path / "REPORT.md")]
    code = (
        "import sys, pytest\n"
        f"bad = pytest.main(['bench', '-q', '-p', 'no:cacheprovider', '--encoders', 'bogus', *{out!r}])\n"
        "good = pytest.main(['bench', '--co', '-q', '-p', 'no:cacheprovider', '--backbones',"
        f" 'smolvla,pi05', '--encoders', 'pixels,dinov2_s', *{out!r}])\n"
        "loaded = {m.split('.')[0] for m in sys.modules} & {'lerobot', 'lerobot_policy_graft'}\n"
        "print('RESULT', int(bad), int(good), sorted(loaded))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True,
                          text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert "RESULT 4 0 []" in done.stdout, done.stdout[-2000:] + done.stderr[-2000:]
