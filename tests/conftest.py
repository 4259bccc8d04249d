"""The harness's own tests run in the offline world, always."""

import os

for _var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
    os.environ[_var] = "1"
os.environ.setdefault("GRAFTBENCH_QUIET", "1")

import gc  # noqa: E402

import pytest  # noqa: E402

# Full (generation-2) collections 10x rarer than CPython's default (700, 10, 10). A test process
# holds ~540,000 tracked objects once torch, LeRobot and the tiny world are loaded, so each full
# collection walks them all (~0.5-1 s), and the default ran one every few seconds of test work:
# measured on test_grid_plugin + test_newcomer + test_startup + the quick known answers
# (57 tests), 9 full collections took 4.5 s of 133 s; with this, 1 took 1.0 s. Younger
# generations are collected as before, so short-lived cycles are still freed promptly.
gc.set_threshold(700, 10, 100)


@pytest.fixture(autouse=True)
def no_leaked_settings():
    """A test leaves graftbench's and the hub's environment as it found it: a GRAFTBENCH_CACHE
    left behind sends every later test of its worker to an empty cache (measured: one leak made
    a 10 s test train a release and take 114 s). Set them with monkeypatch."""
    def settings():
        return {k: v for k, v in os.environ.items() if k.startswith(("GRAFTBENCH_", "HF_"))}

    before = settings()
    yield
    after = settings()
    if after != before:
        changed = sorted(k for k in before.keys() | after.keys() if before.get(k) != after.get(k))
        for k in changed:  # put it back, so that only this test fails, not every later one
            if k in before:
                os.environ[k] = before[k]
            else:
                del os.environ[k]
        pytest.fail(f"the test left {', '.join(changed)} changed in os.environ: set it with "
                    "monkeypatch.setenv so that it is restored", pytrace=False)


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


# `pytest tests -n 2` (the README's command; bench.plugin gives each worker its share of the
# CPUs): every module is one group, so a module's fixtures and measured cells stay in one worker,
# except the modules in SPLIT (the known answers: one group per backbone, each about the size of
# a whole module). xdist's own --dist loadgroup cannot carry groups under pytest 9.2 (bench.plugin's
# scheduler says why), so the groups are read from the node ids here. They go out longest first
# (a long group started last would finish alone): LONGEST_FIRST, from docs/TESTING.md's seconds
# per group under -n 2; the rest keep the collection's order.
SPLIT = {"tests/test_known_answers.py"}  # by the test's parameter id (its backbone)
LONGEST_FIRST = (
    "tests/test_sim_frames.py", "tests/test_known_answers.py[pi05]",
    "tests/test_robustness.py", "tests/test_known_answers.py[pi0]", "tests/test_hub_world.py",
    "tests/test_sim_demos.py", "tests/test_known_answers.py[smolvla]", "tests/test_xdist.py",
    "tests/test_own_policy.py", "tests/test_export.py", "tests/test_startup.py",
    "tests/test_claims.py", "tests/test_screening.py", "tests/test_plugin_standalone.py",
    "tests/test_executors.py", "tests/test_sim_batched.py", "tests/test_screen_run.py",
    "tests/test_tuned_encoder.py", "tests/test_user_encoder.py", "tests/test_short_graft.py",
    "tests/test_sim_rollout.py", "tests/test_gpu_smoke.py", "tests/test_suites.py",
    "tests/test_robust_loop.py", "tests/test_pack_grafts.py", "tests/test_tiers.py",
    "tests/test_grid_plugin.py", "tests/test_screen.py", "tests/test_newcomer.py",
    "tests/test_projector_reuse.py", "tests/test_known_answers.py", "tests/test_gridfile.py",
    "tests/test_features.py", "tests/test_determinism.py",
)


def xdist_group(nodeid: str) -> str:
    """tests/test_x.py::test_y[a] -> 'tests/test_x.py' ('tests/test_x.py[a]' in SPLIT modules)."""
    module, _, name = nodeid.partition("::")
    if module in SPLIT and name.endswith("]") and "[" in name:
        return f"{module}[{name[name.index('[') + 1:-1]}]"
    return module


@pytest.hookimpl(tryfirst=True, optionalhook=True)  # before bench.plugin's (grid cells only)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    if config.getvalue("dist") != "loadgroup":  # -n alone means loadgroup (bench.plugin)
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_group(nodeid)

    config.option.loadscopereorder = False  # keep LONGEST_FIRST, not xdist's most-tests-first
    return ModuleScheduling(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if hasattr(config, "workerinput"):  # the controller schedules groups in this order
        rank = {group: i for i, group in enumerate(LONGEST_FIRST)}
        items.sort(key=lambda item: rank.get(xdist_group(item.nodeid), len(rank)))
