"""bench.cell.executors: the selected cells as ONE submitit job array, collected per cell.

(a) submitit's LocalExecutor end to end through `pytest bench --executor submitit-local`: the
    records equal those of the default local executor, number for number;
(b) the Slurm path on a mocked cluster (the idea of submitit's own `mocked_slurm`, in
    submitit/slurm/test_slurm.py): sbatch/sacct are stand-ins, the test plays the cluster by
    running each array task's pickle, and the results come back per cell.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path
from unittest.mock import patch

import pytest

from bench.grid.cells import CellSpec
from bench.cell.executors import CellArray, CellJob, SlurmOptions
from bench.grid.protocol import TINY, with_overrides

SLICE = ["--backbones", "pi05", "--suites", "spatial", "--encoders", "pixels,blind",
         "--seeds", "0", "--controls", "none", "--steps", "5"]


def records(results: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in sorted((results / "cells").glob("*.json"))}


def measured(record: dict) -> dict:
    """The numbers of a record (not its timings, host or creation time)."""
    keys = ("mse", "per_window", "per_task", "per_horizon", "loss_curve", "trainable_params")
    return {k: record[k] for k in keys}


@pytest.mark.slow  # two fresh interpreters: the submitit tasks
def test_submitit_local_gives_the_local_records(tmp_path, bench_cli, one_torch_thread):
    """The local reference and the submitit controller run in this process (one torch thread, as
    the tasks' OMP_NUM_THREADS=1); the cells of the submitit run in its tasks' fresh
    interpreters: same numbers."""
    local_run = bench_cli(tmp_path / "local", *SLICE, "-q")
    assert local_run.returncode == 0, local_run.stdout[-3000:]
    done = bench_cli(tmp_path / "submitit", *SLICE, "-q", "--executor", "submitit-local",
                     env={"OMP_NUM_THREADS": "1", "GRAFTBENCH_QUIET": "1", "HF_HUB_OFFLINE": "1"})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    local = records(tmp_path / "local" / "results")
    submitted = records(tmp_path / "submitit" / "results")
    assert sorted(local) == sorted(submitted) == ["pi05-spatial-blind-seed0",
                                                  "pi05-spatial-pixels-seed0"]
    for cell_id in local:
        assert measured(submitted[cell_id]) == measured(local[cell_id]), cell_id
    # Each cell ran in its own submitit task (a log folder per job), not in the pytest process.
    logs = list((tmp_path / "submitit" / "results" / "submitit").glob("*_result.pkl"))
    assert len(logs) == 2, done.stdout[-2000:]


# -- the Slurm path on a mocked cluster --------------------------------------------------------
class FakeSlurm:
    """Stand-ins for sbatch, sacct and scancel, as submitit's own tests mock them."""

    def __init__(self) -> None:
        self.sbatch_scripts: list[str] = []
        self.states: dict[str, str] = {}  # "4242_0" -> state
        self.next_id = 4242

    def command_function(self, command, *args, **kwargs):  # replaces utils.CommandFunction
        return lambda: self(command).decode()

    def __call__(self, command, *args, **kwargs) -> bytes:  # replaces subprocess.check_output
        program = command[0]
        if program == "sbatch":
            script = Path(command[1]).read_text()
            self.sbatch_scripts.append(script)
            job_id, self.next_id = str(self.next_id), self.next_id + 1
            size = re.search(r"--array=0-(\d+)", script)
            for task in range(int(size.group(1)) + 1 if size else 1):
                self.states[f"{job_id}_{task}" if size else job_id] = "RUNNING"
            return f"Submitted batch job {job_id}\n".encode()
        if program == "sacct":
            lines = [f"{job}|{state}" for job, state in self.states.items()]
            return "\n".join(["JobID|State", *lines]).encode()
        if program == "scancel":
            return b""
        raise ValueError(f"unexpected command {command}")

    def run_task(self, job, monkeypatch) -> None:
        """Play the cluster: run the array task's pickle in its Slurm environment."""
        from submitit.core import submission

        array_id, task = job.job_id.split("_")
        for name, value in {"SUBMITIT_EXECUTOR": "slurm", "SLURM_JOB_ID": job.job_id,
                            "SLURM_ARRAY_JOB_ID": array_id, "SLURM_ARRAY_TASK_ID": task}.items():
            monkeypatch.setenv(name, value)
        submission.process_job(job.paths.folder)
        self.states[job.job_id] = "COMPLETED"


def fake_cell_job(job: CellJob) -> dict:
    """A cheap stand-in for run_cell_job: a record that names its cell and where it ran."""
    return {"cell_id": job.cell.id, "slurm_task": os.environ["SLURM_ARRAY_TASK_ID"],
            "results_dir": job.results_dir}


def test_slurm_path_submits_one_array_and_collects_per_cell(tmp_path, monkeypatch):
    from submitit.slurm.slurm import SlurmJob

    profile = with_overrides(TINY, backbones=("pi05",), suites=("spatial",), seeds=(0, 1, 2))
    cells = [CellSpec("graft", "pi05", "spatial", seed, "pixels") for seed in (0, 1, 2)]
    cluster = FakeSlurm()
    pythonpath = os.environ.get("PYTHONPATH")
    options = SlurmOptions(partition="gpu", time_min=90, gpus_per_task=1, array_parallelism=2)
    with patch("submitit.core.utils.CommandFunction", new=cluster.command_function), \
            patch("subprocess.check_output", new=cluster), \
            patch("shutil.which", new=lambda name: "/usr/bin/" + name):
        try:
            array = CellArray("slurm", tmp_path / "submitit", options, job_fn=fake_cell_job)
            jobs = array.submit([CellJob(c, profile, str(tmp_path), str(tmp_path)) for c in cells])

            assert len(cluster.sbatch_scripts) == 1, "one sbatch call for the whole selection"
            script = cluster.sbatch_scripts[0]
            for line in ("#SBATCH --array=0-2%2", "#SBATCH --partition=gpu", "#SBATCH --time=90",
                         "#SBATCH --gpus-per-task=1", "#SBATCH --job-name=graftbench"):
                assert line in script, f"{line!r} not in the sbatch file:\n{script}"
            assert [j.job_id for j in jobs] == ["4242_0", "4242_1", "4242_2"]
            assert os.environ.get("PYTHONPATH") == pythonpath, "submission restores the env"

            for job in jobs:
                cluster.run_task(job, monkeypatch)
            results = {c.id: array.result(c.id) for c in cells}
        finally:
            SlurmJob.watcher.clear()
    assert {cid: r["cell_id"] for cid, r in results.items()} == {c.id: c.id for c in cells}
    assert sorted(r["slurm_task"] for r in results.values()) == ["0", "1", "2"]
    with pytest.raises(KeyError, match="was not submitted"):
        array.result("pi05-spatial-blind-seed0")
