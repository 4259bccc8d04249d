"""The harness's own tests run in the offline world, always."""

import os

for _var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
    os.environ[_var] = "1"
os.environ.setdefault("GRAFTBENCH_QUIET", "1")

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def tiny_ws(tmp_path_factory):
    """The tiny profile's workspace (shared caches: released checkpoints, suites, features) with
    a private results store, shared by the tests that run real cells."""
    from bench.grid.protocol import TINY
    from bench.results.store import ResultStore
    from tests.worlds import lent_workspace

    return lent_workspace(TINY, ResultStore(tmp_path_factory.mktemp("results")))


@pytest.fixture
def tiny_workspace(tmp_path):
    """`tiny_workspace(profile)`: a workspace of `profile` with a results store of this test's
    own, lending the session's loaded tiny world (tests/worlds.py)."""
    from bench.results.store import ResultStore
    from tests.worlds import lent_workspace

    return lambda profile: lent_workspace(profile, ResultStore(tmp_path / "results"))


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module of tiny-policy tests, restored afterwards: tiny ops are all
    thread overhead (with 2 shared cores a 10-step sample took 1.3 s on 2 threads, 0.1 s on 1)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def bench_cli():
    """`bench_cli(folder, *args)`: `pytest bench *args` run in this process (tests/bench_inprocess.py)
    with its results in folder/results and its report at folder/REPORT.md."""
    from tests.bench_inprocess import run_bench

    def run(folder, *args: str, **kwargs):
        return run_bench("--results-dir", str(folder / "results"),
                         "--report", str(folder / "REPORT.md"), *args, **kwargs)

    return run
