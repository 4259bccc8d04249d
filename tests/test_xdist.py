"""`pytest bench` on two xdist workers (what it takes by default on 2 CPUs: no -n given) gives
the records and REPORT.md numbers of a serial run (the parallel run in a fresh interpreter: xdist
workers are processes; the serial one in this process, on one torch thread as each worker).

Two backbones; in the tiny world each cell and screen goes out on its own as a worker frees up
(bench.scheduling.cell_units); the controller alone writes REPORT.md from the shared results
store. Both runs screen too (`--screen --screen-keep all`, the short-graft tier deselected):
each screen is measured once, whichever worker's case or selection reaches it first, and the
screens give the serial run's numbers.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ondisk.paths import REPO_ROOT

pytestmark = pytest.mark.slow  # fresh interpreters (docs/TESTING.md: tiers)

# 20 projector steps: what is compared is the bits of two runs, not how well they trained.
SLICE = ["--backbones", "pi05,smolvla", "--suites", "spatial", "--encoders", "pixels,blind",
         "--seeds", "0", "--controls", "none", "--steps", "20",
         "--screen", "--screen-keep", "all", "-k", "not test_short_graft"]
# One torch thread per process in BOTH runs: the thread count must not differ between them (the
# in-process serial run would otherwise take the CPUs the load leaves free: bench.session).
ENV = {"OMP_NUM_THREADS": "1", "GRAFTBENCH_QUIET": "1", "HF_HUB_OFFLINE": "1"}


def run_grid(results: Path, *extra: str) -> str:
    cmd = [sys.executable, "-m", "pytest", "bench", "-p", "no:randomly", "-p", "no:cacheprovider",
           *SLICE, "--results-dir", str(results), "--report", str(results / "REPORT.md"), *extra]
    done = subprocess.run(cmd, cwd=REPO_ROOT, env={**os.environ, **ENV}, capture_output=True,
                          text=True, timeout=600)
    # Every case must pass: two runs that fail alike are not two runs that agree.
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done.stdout


def numbers(results: Path) -> dict:
    cells = {p.stem: json.loads(p.read_text()) for p in sorted((results / "cells").glob("*.json"))}
    return {cid: (r["mse"], r["per_window"], r["loss_curve"]) for cid, r in cells.items()}


def report_before_provenance(results: Path) -> str:
    """REPORT.md up to its provenance section (paths, timings and dates differ by design), less
    the screen section (its table and cost give seconds; the screens' numbers: screen_numbers)."""
    text = (results / "REPORT.md").read_text().split("## Provenance")[0]
    start = text.index("## Screening many encoders")
    return text[:start] + text[text.index("\n## ", start + 1):]


def screen_numbers(results: Path) -> dict:
    """{screen id: its proxies, entropy and sizes}: the screen records less their seconds."""
    out = {}
    for path in sorted((results / "screens").glob("*.json")):
        scores = json.loads(path.read_text())["scores"]
        out[path.stem] = {k: v for k, v in scores.items() if k != "seconds"}
    return out


@pytest.fixture(scope="module")
def serial_and_parallel(tmp_path_factory, one_torch_thread):
    """The serial run in this process (one torch thread, as each worker's), the -n 2 run in
    fresh interpreters (xdist's workers are processes)."""
    from tests.bench_inprocess import run_bench

    root = tmp_path_factory.mktemp("xdist")
    serial = root / "serial"
    done = run_bench(*SLICE, "-q", "--results-dir", str(serial), "--report",
                     str(serial / "REPORT.md"), figures=True, env=ENV)
    assert done.returncode == 0, done.stdout[-3000:]
    serial_out = done.stdout
    # The user's command as typed: without -n, the tiny world takes 2 workers on 2 CPUs or more
    # (bench.scheduling.default_workers); a machine with one CPU is given -n 2.
    given = [] if len(os.sched_getaffinity(0)) >= 2 else ["-n", "2"]
    parallel_out = run_grid(root / "parallel", *given, "-v")
    assert "created: 2/2 workers" in parallel_out, parallel_out[:2000]
    return root / "serial", root / "parallel", serial_out, parallel_out


def test_parallel_records_equal_serial_records(serial_and_parallel):
    serial, parallel, _, _ = serial_and_parallel
    a, b = numbers(serial), numbers(parallel)
    assert len(a) == 4 and sorted(a) == sorted(b)
    for cell_id in a:
        assert a[cell_id] == b[cell_id], f"{cell_id}: -n 2 changed the numbers"
    # The controller collects nothing itself: it takes the selection from its workers.
    grids = [json.loads((r / "grid.json").read_text())["expected"] for r in (serial, parallel)]
    assert sorted(grids[0]) == sorted(grids[1]) == sorted(a)


def test_parallel_report_equals_serial_report(serial_and_parallel):
    serial, parallel, _, _ = serial_and_parallel
    assert report_before_provenance(parallel) == report_before_provenance(serial)
    assert len(screen_numbers(serial)) == 4
    assert screen_numbers(parallel) == screen_numbers(serial)
    summary = [json.loads((r / "REPORT_summary.json").read_text()) for r in (serial, parallel)]
    assert summary[0] == summary[1]


def test_both_workers_work_and_every_screen_case_runs_once(serial_and_parallel):
    """In the tiny world every cell and screen is a unit of its own (bench.scheduling.cell_units):
    both workers take cells, and a backbone's selection that needs a screen the other worker
    holds waits for its lock and resumes it (the screens' numbers are the serial run's:
    test_parallel_report_equals_serial_report)."""
    _, _, _, out = serial_and_parallel
    counts = re.search(r"screens 4: measured (\d), resumed from store (\d), failed 0", out)
    assert counts and sum(map(int, counts.groups())) == 4, out[-2000:]
    ran_on = re.findall(r"\[(gw\d+)\].*PASSED bench/test_grid.py::test_(graft|screen)\[", out)
    assert len(ran_on) == 8 and {w for w, _ in ran_on} == {"gw0", "gw1"}, out[-2000:]
