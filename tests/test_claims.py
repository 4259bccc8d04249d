"""A claim on a cell (ResultStore.cell_lock, taken by GraftSession.run): two runs on one
results dir measure each cell once, the later one waiting for the claimant's record; a killed
claimant frees its claim (a flock); a record that cannot be read is named, moved aside to
unreadable/ and measured again, and the report counts it.

Time: the two-run test (slow: a second interpreter) 26 s on this 2-core machine beside one
other busy process, 54 s beside two; the others ~3 s together once the tiny world is loaded."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

from bench.results.store import ResultStore
from ondisk.paths import REPO_ROOT

# Two evaluation-only cells of the tiny world (no projector trained): ~0.5 s each.
TWO_CELLS = ["--backbones", "pi05", "--suites", "spatial", "--encoders", "pixels", "--seeds",
             "0", "--controls", "native,zero_image", "-k", "native"]
CELL_IDS = ["pi05-spatial-native-seed0", "pi05-spatial-native-zero_image_eval-seed0"]


def test_a_killed_claimant_frees_its_claim(tmp_path):
    """The claimant is another process, killed with SIGKILL: no cleanup of its own runs."""
    store = ResultStore(tmp_path)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from bench.results.store import ResultStore\n"
         f"with ResultStore({str(tmp_path)!r}).cell_lock('c'):\n"
         "    print('held', flush=True); time.sleep(60)"],
        stdout=subprocess.PIPE, text=True, cwd=REPO_ROOT)
    try:
        assert holder.stdout.readline().strip() == "held"
        waited, got = threading.Event(), threading.Event()

        def claim():
            with store.cell_lock("c", on_wait=waited.set):
                got.set()

        waiter = threading.Thread(target=claim, daemon=True)
        waiter.start()
        assert waited.wait(5) and not got.wait(0.3)  # held elsewhere: it waits
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    assert got.wait(5)  # the kernel released the dead claimant's flock


def test_a_claim_is_reentrant_in_its_thread(tmp_path):
    """A --screen-by short selection claims a short graft, then runs it through the session,
    which claims it again: the same thread must not wait on itself."""
    store = ResultStore(tmp_path)
    with store.cell_lock("c"), store.cell_lock("c"):
        pass


def test_an_unreadable_record_is_named_moved_aside_measured_again_and_counted(bench_cli, tmp_path):
    first = bench_cli(tmp_path, *TWO_CELLS)
    assert first.returncode == 0 and "measured 2, resumed from store 0" in first.stdout, first.stdout
    path = tmp_path / "results" / "cells" / f"{CELL_IDS[0]}.json"
    truncated = path.read_bytes()[: path.stat().st_size // 2]
    path.write_bytes(truncated)

    again = bench_cli(tmp_path, *TWO_CELLS)
    assert again.returncode == 0 and "measured 1, resumed from store 1" in again.stdout, again.stdout
    (aside,) = (tmp_path / "results" / "unreadable").iterdir()
    assert aside.read_bytes() == truncated and aside.name.startswith(CELL_IDS[0] + ".")
    said = [line for line in again.stdout.splitlines() if line.startswith("set aside: ")]
    assert len(said) == 1 and re.fullmatch(
        re.escape(f"set aside: cells/{CELL_IDS[0]}.json is unreadable (JSONDecodeError: ")
        + r"[^\n]+" + re.escape(f"): moved to unreadable/{aside.name}; {CELL_IDS[0]} is "
                                 "measured again"), said[0]), again.stdout
    assert path.is_file() and len(path.read_bytes()) > len(truncated)
    report = (tmp_path / "REPORT.md").read_text()
    assert ("0 unreadable files skipped, 1 unreadable record(s) moved aside to `unreadable/` and "
            "measured again") in report


def counts(screen: str) -> tuple[int, int]:
    """(measured, resumed from store) of a run's summary line."""
    found = re.findall(r"measured (\d+), resumed from store (\d+)", screen)
    assert len(found) == 1, screen[-2000:]
    return int(found[0][0]), int(found[0][1])


@pytest.mark.slow  # a second interpreter: the other run
def test_two_runs_on_one_results_dir_measure_each_cell_once(bench_cli, tmp_path):
    """Run A (another process) measures the two cells, each taking 2 s more (tests/slow_cells);
    run B starts on the same results dir while A measures the first, waits for each claim and
    resumes A's record. Without the claim, B measured the cell A was measuring (4
    measurements for 2 cells)."""
    marks = tmp_path / "marks"
    env = {**os.environ, "GRAFTBENCH_TEST_MARKS": str(marks), "GRAFTBENCH_TEST_CELL_DELAY": "2",
           "OMP_NUM_THREADS": "1"}
    other = subprocess.Popen(
        [sys.executable, "-m", "pytest", str(REPO_ROOT / "bench"), "-p", "no:cacheprovider",
         "-n", "0", "-p", "tests.slow_cells", *TWO_CELLS, "--results-dir", str(tmp_path / "results"),
         "--report", str(tmp_path / "A.md")],
        cwd=REPO_ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + 180
    while not any(marks.glob(f"{CELL_IDS[0]}.*")) and other.poll() is None:
        assert time.monotonic() < deadline, "the other run never started its first cell"
        time.sleep(0.1)
    mine = bench_cli(tmp_path, *TWO_CELLS, "-p", "tests.slow_cells",
                     env={"GRAFTBENCH_TEST_MARKS": str(marks), "GRAFTBENCH_QUIET": None})
    theirs = other.communicate(timeout=180)[0]
    assert other.returncode == 0 and mine.returncode == 0, theirs[-3000:] + mine.stdout[-3000:]
    assert sorted(p.name.rsplit(".", 1)[0] for p in marks.iterdir()) == CELL_IDS  # once each
    # A measured the first cell (B waited for it, below); the second goes to whichever run claims
    # it first once the first is done (B, when A is slow to reach it): either way each cell is
    # measured in one run and resumed from the store in the other.
    (a_measured, a_resumed), (b_measured, b_resumed) = counts(theirs), counts(mine.stdout)
    assert a_measured >= 1 and (a_measured + b_measured, a_resumed + b_resumed) == (2, 2), (
        theirs[-2000:] + mine.stdout[-2000:])
    assert (f"{CELL_IDS[0]}: another process is measuring it (its claim "
            f"{tmp_path / 'results' / '.claims' / CELL_IDS[0]}.lock); waiting for its record"
            in mine.stdout), mine.stdout[-3000:]
