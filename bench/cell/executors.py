"""Where cells run: in the pytest process (local, the default) or as ONE submitit job array.

`--executor slurm` submits every selected cell that has no current record as one Slurm job array
through submitit; `--executor submitit-local` does the same with submitit's LocalExecutor (one
subprocess per cell on this machine: the test stand-in for a cluster). The cell service decides
which cells those are and plans them; it hands the plans to a `JobArray`, which submits them and
returns each cell's result, and calls nothing of the service's back. Each array task runs
`run_cell_job` in a fresh process: it rebuilds a Workspace from plain, picklable inputs (cell spec,
profile, paths), runs the cell and writes its record to the shared results store. Each pytest case
then waits for its own task and reports that task's record (or its traceback).

No scheduling of our own: submitit writes the sbatch file, submits, polls sacct and collects.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator, Sequence

from bench.grid.cells import CellSpec
from ondisk.paths import REPO_ROOT, cache_dir
from bench.grid.protocol import Profile
from bench.results.record import Record
from bench.cell.plan import CellPlan, CellResult
from bench.cell.service import RunSettings
from bench.sim.batching import IN_PROCESS, Batching

EXECUTORS = ("local", "slurm", "submitit-local")


@dataclass(frozen=True)
class SlurmOptions:
    """What `--slurm-*` sets on the sbatch file (submitit SlurmExecutor parameter names)."""

    partition: str | None = None
    time_min: int = 240
    gpus_per_task: int = 1
    cpus_per_task: int = 8
    array_parallelism: int = 64
    setup: tuple[str, ...] = ()  # shell lines run before the task, e.g. "module load cuda"


@dataclass(frozen=True)
class CellJob:
    """Everything one array task needs, as plain picklable values (no live objects)."""

    cell: CellSpec
    profile: Profile
    results_dir: str
    cache_dir: str
    # How the run measures (bench.cell.service.RunSettings); a task always measures (rerun):
    # the session submits only cells without a current record.
    settings: RunSettings = RunSettings()
    rollout_batching: Batching = IN_PROCESS  # --rollout-batch, --rollout-envs


def run_cell_job(job: CellJob) -> Record:
    """Array-task entry point, in a fresh process: rebuild the workspace, then the cell through
    the cell service (bench.cell.service: claim, plan, measure, record or failure record)."""
    os.environ["GRAFTBENCH_CACHE"] = job.cache_dir
    if job.profile.offline:  # before anything imports huggingface_hub
        for var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
            os.environ[var] = "1"
    from bench.results.store import ResultStore
    from bench.cell.service import CellService
    from bench.progress import LogSink
    from bench.resources.workspace import Workspace

    store = ResultStore(Path(job.results_dir))
    s = replace(job.settings, rerun=True)
    # The task's progress goes to its log (submitit's <folder>/*_log.err): an hour-long
    # task whose log stays empty cannot be told from a hung one (GRAFTBENCH_QUIET=1 silences it).
    ws = Workspace(job.profile, store, progress=LogSink(), cache=Path(job.cache_dir),
                   rollouts=s.rollouts, feature_dtype=s.feature_dtype,
                   rollout_batching=job.rollout_batching)
    return CellService(job.profile, store, lambda: ws, s).run(job.cell)


def make_executor(kind: str, folder: Path, slurm: SlurmOptions):
    """A submitit executor writing its pickles and logs under `folder`."""
    import submitit

    if kind == "slurm":
        executor = submitit.SlurmExecutor(folder=folder)
        params = dict(
            time=slurm.time_min, gpus_per_task=slurm.gpus_per_task,
            cpus_per_task=slurm.cpus_per_task, array_parallelism=slurm.array_parallelism,
            ntasks_per_node=1, job_name="graftbench", setup=list(slurm.setup),
        )
        if slurm.partition:
            params["partition"] = slurm.partition
        executor.update_parameters(**params)
        return executor
    if kind == "submitit-local":
        executor = submitit.LocalExecutor(folder=folder)
        executor.update_parameters(timeout_min=slurm.time_min)
        return executor
    raise ValueError(f"executor {kind!r} does not submit jobs; valid: {', '.join(EXECUTORS[1:])}")


@contextlib.contextmanager
def _repo_importable() -> Iterator[None]:
    """PYTHONPATH holds the repo while submitting: sbatch (--export=ALL by default) and the local
    executor's subprocesses copy the environment at submission, and the task unpickles `bench`."""
    previous = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO_ROOT), previous) if p)
    try:
        yield
    finally:
        if previous is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = previous


@dataclass
class CellArray:
    """The selected cells, submitted as ONE job array on first use; one job per cell."""

    kind: str
    folder: Path
    slurm: SlurmOptions = field(default_factory=SlurmOptions)
    job_fn: Callable[[CellJob], dict] = run_cell_job
    jobs: dict[str, object] = field(default_factory=dict)  # cell id -> submitit Job

    def submit(self, cell_jobs: list[CellJob]) -> list:
        """Submit all `cell_jobs` as one array (submitit map_array); returns the submitit jobs."""
        if not cell_jobs:
            return []
        executor = make_executor(self.kind, self.folder, self.slurm)
        with _repo_importable():
            jobs = executor.map_array(self.job_fn, cell_jobs)
        for cell_job, job in zip(cell_jobs, jobs):
            self.jobs[cell_job.cell.id] = job
        return jobs

    def result(self, cell_id: str) -> dict:
        """Wait for the cell's task; its record, or the task's error (with its traceback)."""
        if cell_id not in self.jobs:
            raise KeyError(f"cell {cell_id!r} was not submitted; submitted: {sorted(self.jobs)}")
        return self.jobs[cell_id].result()


@dataclass
class JobArray:
    """The cell service's way to a job array: the plans it hands over, submitted once as ONE
    `CellArray` (a CellJob each, with this run's profile, results dir, cache and settings), and
    each plan's result: the record its task wrote to the shared store."""

    cells: CellArray
    profile: Profile
    results_dir: Path
    settings: RunSettings
    rollout_batching: Batching = IN_PROCESS

    def submit(self, plans: Sequence[CellPlan]) -> None:
        """Submit the cells of `plans` as one array (the service chose and planned them)."""
        paths = (str(self.results_dir), str(cache_dir()))
        self.cells.submit([CellJob(p.cell, self.profile, *paths, self.settings,
                                   self.rollout_batching) for p in plans])

    def result(self, cell_plan: CellPlan) -> CellResult:
        """Wait for the task of `cell_plan`'s cell: its record, already stored (or the task's
        error; KeyError for a cell that was not submitted)."""
        return CellResult(self.cells.result(cell_plan.cell.id), stored=True)
