"""A newcomer's first run, `pytest bench` as typed (in this process: tests/bench_inprocess.py):
progress without -s, a report that belongs to its results, nothing written when nothing
finished, bad options in one line."""

from __future__ import annotations

import re

import pytest

from ondisk.paths import REPO_ROOT

ONE_CELL = ["--backbones", "pi05", "--suites", "spatial", "--encoders", "blind", "--seeds", "0",
            "--controls", "none", "--steps", "5"]


@pytest.fixture
def run_bench():
    """`run_bench(*args, quiet=False)`: GRAFTBENCH_QUIET unset unless quiet, a workspace built as
    a user's run builds it (torch threads chosen and printed)."""
    from tests.bench_inprocess import run_bench as run

    def bench(*args: str, quiet: bool = False):
        return run(*args, shared=False, env={"GRAFTBENCH_QUIET": "1" if quiet else None})

    return bench


def test_first_run_shows_progress_and_leaves_the_repo_report_alone(run_bench, tmp_path):
    committed = REPO_ROOT / "REPORT.md"
    before = committed.read_bytes() if committed.exists() else None
    out = run_bench(*ONE_CELL, "--results-dir", str(tmp_path / "results"))  # no -s, no --report
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    # Progress through pytest's capture: the thread choice, the cell with its steps, its MSE.
    assert re.search(r"\[graftbench\] torch threads: \d+ \(", out.stdout)
    assert "[graftbench] cell 1/1 pi05-spatial-blind-seed0: 5 projector steps" in out.stdout
    assert re.search(r"\[graftbench\] pi05-spatial-blind-seed0: MSE \d\.\d{4} normalised", out.stdout)
    # The session summary.
    assert "measured 1, resumed from store 0, failed 0" in out.stdout
    assert re.search(r"answer: ", out.stdout)
    # The report goes beside its results; the repo's REPORT.md is byte-identical.
    report = tmp_path / "results" / "REPORT.md"
    assert report.is_file() and f"report: {report}" in out.stdout
    assert (committed.read_bytes() if committed.exists() else None) == before
    text = report.read_text()
    assert str(tmp_path) not in text and str(REPO_ROOT) not in text  # no machine paths
    assert not re.search(r"=\?|`\?`|\(\?\)|: \?$", text, flags=re.M)  # no placeholders

    quiet = run_bench(*ONE_CELL, "--results-dir", str(tmp_path / "results"), quiet=True)
    assert "[graftbench] cell" not in quiet.stdout  # resumed, and quiet anyway
    assert "resumed from store 1" in quiet.stdout
    assert f"report: {report} left as it was" in quiet.stdout


def test_runs_that_finish_no_cell_write_no_report(run_bench, tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    earlier = "# graftbench report\n\nan earlier report\n"  # its marker: bench.outputs
    (results / "REPORT.md").write_text(earlier)
    collect = run_bench(*ONE_CELL, "--results-dir", str(results), "--co", quiet=True)
    assert collect.returncode == 0, collect.stdout[-2000:]
    stopped = run_bench("--profile", "paper", "--backbones", "pi05", "--suites", "spatial",
                        "--encoders", "dinov2_s", "--controls", "none", "--seeds", "0",
                        "--results-dir", str(results), quiet=True)
    assert stopped.returncode == 4, stopped.stdout[-2000:]  # preflight: artifacts missing
    assert (results / "REPORT.md").read_text() == earlier


@pytest.mark.parametrize("args, message", [
    (["--steps", "-1"], "--steps: steps = -1 is out of range; give steps >= 1"),
    (["--steps", "0"], "--steps: steps = 0 is out of range; give steps >= 1"),
    (["--seeds", "0,abc"], "--seeds 0,abc: ['abc'] not a non-negative integer"),
])
def test_bad_options_are_one_line_usage_errors(run_bench, args, message):
    out = run_bench(*args, "--co", quiet=True)
    text = out.stdout + out.stderr
    assert out.returncode == 4 and message in text
    assert "INTERNALERROR" not in text and "Traceback" not in text


def test_unwritable_results_dir_is_a_usage_error_not_an_internal_error(run_bench, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    out = run_bench(*ONE_CELL, "--results-dir", str(blocker / "results"), "--co", quiet=True)
    text = out.stdout + out.stderr
    assert out.returncode == 4 and "--results-dir:" in text and "not writable" in text
    assert "INTERNALERROR" not in text
