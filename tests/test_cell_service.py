"""One way to measure a cell (bench.cell.service): the session, every executor and the screen go
through `CellService`, and nothing outside the session writes into it. Read from the code (AST),
then checked by a spy on the array task's entry point."""

from __future__ import annotations

import ast
import os

import pytest

from ondisk.paths import REPO_ROOT

SERVICE = "bench/cell/service.py"


def _sources() -> dict[str, ast.Module]:
    """The code that runs cells (benchmarks/ times the parts on their own, so is left out)."""
    paths = [p for pkg in ("bench", "backbones", "encoders", "ondisk", "scripts", "plugins")
             for p in (REPO_ROOT / pkg).rglob("*.py")]
    return {p.relative_to(REPO_ROOT).as_posix(): ast.parse(p.read_text()) for p in paths}


def _importers(name: str, module: str) -> set[str]:
    """Files that import `name` from `module` (at any depth of the file)."""
    out = set()
    for path, tree in _sources().items():
        for node in ast.walk(tree):
            if (isinstance(node, ast.ImportFrom) and node.module == module
                    and any(a.name == name for a in node.names)):
                out.add(path)
    return out


@pytest.mark.parametrize("name, module", [
    ("measure", "bench.cell.runner"),  # a cell measured in this process
    ("measure_screen", "bench.screen.measure"),  # a screen measured
])
def test_only_the_service_calls_the_measurements(name, module):
    assert _importers(name, module) == {SERVICE}


@pytest.mark.parametrize("path, calls", [
    ("bench/session.py", {"CellService"}),  # serial runs and xdist workers
    ("bench/cell/executors.py", {"CellService"}),  # each submitit / Slurm array task
    ("bench/cell/screening.py", {"screen", "run"}),  # the screens and the short grafts
])
def test_every_executor_and_the_screen_go_through_the_service(path, calls):
    tree = _sources()[path]
    called = {node.func.attr if isinstance(node.func, ast.Attribute) else node.func.id
              for node in ast.walk(tree) if isinstance(node, ast.Call)
              and isinstance(node.func, (ast.Attribute, ast.Name))}
    assert calls <= called
    if path == "bench/cell/screening.py":  # through `self.cells`, the service it was given
        through = {node.func.attr for node in ast.walk(tree) if isinstance(node, ast.Call)
                   and isinstance(node.func, ast.Attribute)
                   and isinstance(node.func.value, ast.Attribute)
                   and node.func.value.attr == "cells"}
        assert calls <= through


def _session_names(tree: ast.Module) -> set[str]:
    """Names a file gives a GraftSession: gs, graft_session, and any name bound from
    `config.stash[SESSION_KEY]` (pytest's own `session` is another object)."""
    names = {"gs", "graft_session"}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Subscript)
                and isinstance(node.value.slice, ast.Name) and node.value.slice.id == "SESSION_KEY"):
            names |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    return names


def test_nothing_outside_the_session_assigns_to_it():
    """The plugin and the tests hand the session values through its methods (`collected`,
    `use_seams`), never by setting its attributes."""
    files = {**_sources(), **{p.relative_to(REPO_ROOT).as_posix(): ast.parse(p.read_text())
                              for p in (REPO_ROOT / "tests").glob("*.py")}}
    found = []
    for path, tree in files.items():
        if path == "bench/session.py":
            continue
        names = _session_names(tree)
        for node in ast.walk(tree):
            targets = (node.targets if isinstance(node, ast.Assign)
                       else [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign))
                       else [])
            for t in targets:
                for leaf in (t.elts if isinstance(t, ast.Tuple) else [t]):
                    if (isinstance(leaf, ast.Attribute) and isinstance(leaf.value, ast.Name)
                            and leaf.value.id in names):
                        found.append(f"{path}:{node.lineno} {leaf.value.id}.{leaf.attr}")
    assert not found


def test_the_array_task_measures_through_the_service(tmp_path, monkeypatch):
    """run_cell_job (a submitit / Slurm task's entry point) hands its cell to CellService.run,
    measuring whatever is stored (the session submits only cells without a current record)."""
    from bench.grid.cells import CellSpec
    from bench.grid.kinds import GRAFT
    from bench.grid.protocol import TINY
    from bench.cell import executors, service

    seen = []

    def spy(self, cell):
        seen.append((cell.id, self.settings.rerun, self.settings.feature_dtype, self.claim))
        return "record"

    monkeypatch.setattr(service.CellService, "run", spy)
    # The task points its own process at the job's cache; monkeypatch restores ours afterwards.
    monkeypatch.setenv("GRAFTBENCH_CACHE", os.environ.get("GRAFTBENCH_CACHE", ""))
    cell = CellSpec(GRAFT, "smolvla", "spatial", 0, "pixels")
    job = executors.CellJob(cell, TINY, str(tmp_path / "results"), str(tmp_path / "cache"),
                            service.RunSettings(feature_dtype="bf16"))
    assert executors.run_cell_job(job) == "record"
    assert seen == [(cell.id, True, "bf16", True)]
    assert os.environ["GRAFTBENCH_CACHE"] == str(tmp_path / "cache")


def test_the_service_plans_the_job_array_and_hands_it_the_plans(tmp_path, monkeypatch):
    """--executor: the first cell measured makes the SERVICE plan the array's candidates and hand
    those that do not resume to the job array, once; each cell's record is its own task's (written
    there, not again here); a cell the array was not handed fails in its own failure record. The
    array is handed plans and returns results: it is never handed the service."""
    from types import SimpleNamespace

    from bench.cell import executors, service
    from bench.cell.plan import CellContext, CellPlan
    from bench.grid.cells import CellSpec
    from bench.grid.protocol import TINY
    from bench.results.store import ResultStore, load_failure

    cells = [CellSpec("graft", "pi05", "spatial", seed, "pixels") for seed in (0, 1, 2)]
    resumed = cells[1].id  # its stored record stands for the run: not submitted

    def stand_in_plan(cell, stored, run, **kwargs):
        return CellPlan(cell, CellContext(), resume="its record" if cell.id == resumed else None)

    class Task:  # a finished array task: the record it wrote
        def __init__(self, cell_id):
            self.record = SimpleNamespace(cell_id=cell_id, mse_in=lambda: 0.25,
                                          run=SimpleNamespace(total_s=1.0))

        def result(self):
            return self.record

    batches = []

    class Submitted(executors.CellArray):  # submitit's part played here: each job done
        def submit(self, cell_jobs):
            batches.append(cell_jobs)
            self.jobs.update({j.cell.id: Task(j.cell.id) for j in cell_jobs})

    monkeypatch.setattr(service, "plan", stand_in_plan)
    monkeypatch.setenv("GRAFTBENCH_CACHE", str(tmp_path / "cache"))
    store, settings = ResultStore(tmp_path / "results"), service.RunSettings(feature_dtype="bf16")
    array = executors.JobArray(Submitted("submitit-local", tmp_path / "submitit"), TINY,
                               store.root, settings)
    cells_service = service.CellService(
        TINY, store, lambda: SimpleNamespace(progress=None), settings, job_array=array,
        array_candidates=lambda: cells, claim=False)

    assert cells_service.run(cells[0]).cell_id == cells[0].id
    assert [[j.cell.id for j in batch] for batch in batches] == [[cells[0].id, cells[2].id]]
    job = batches[0][0]
    assert (job.profile, job.results_dir, job.settings) == (TINY, str(store.root), settings)
    assert job.cache_dir == str(tmp_path / "cache")
    assert cells_service.run(cells[1]) == "its record"
    assert cells_service.run(cells[2]).cell_id == cells[2].id
    assert len(batches) == 1, "one array for the run"
    assert store.load(cells[0].id) is None, "the task wrote the record: the service does not"

    unselected = CellSpec("graft", "pi05", "spatial", 0, "blind")
    with pytest.raises(KeyError, match="was not submitted"):
        cells_service.run(unselected)
    assert "was not submitted" in load_failure(store.root, unselected.id).error
    assert len(batches) == 1
