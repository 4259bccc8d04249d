"""The grid's command-line options: declared, parsed into a Profile, and checked at start-up,
each bad value a one-line `pytest.UsageError` naming the option (never an INTERNALERROR)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from bench.grid.gridfile import read_grid_file
from external.paths import REPO_ROOT
from bench.grid.kinds import control_kinds
from bench.grid.protocol import get_profile, with_overrides

DEFAULT_PROFILE = "tiny"


def _csv(value: str | None) -> tuple[str, ...] | None:
    return tuple(v.strip() for v in value.split(",") if v.strip()) if value else None


def pytest_addoption(parser: pytest.Parser) -> None:
    g = parser.getgroup("graftbench", "graftbench grid")
    g.addoption("--profile",
                help="tiny (offline default, 28 cells), tiny-full (136 cells), paper, sim")
    g.addoption("--grid", metavar="FILE.toml",
                help="a study in a TOML file (schema: bench/grid/gridfile.py); its path, sha256 and "
                     "text go into every record. Options given here override its values: "
                     "--profile its base profile, --backbones etc. its lists, --steps its steps")
    g.addoption("--backbones", help="comma list, e.g. smolvla,pi05")
    g.addoption("--encoders", help="comma list of registry names, timm:<model> or "
                                   "PKG.MODULE:FACTORY (an importable module of yours: "
                                   "encoders/user_encoders.py)")
    g.addoption("--suites", help="comma list, e.g. spatial,object")
    g.addoption("--policy", action="append", metavar="NAME=REPO_ID_OR_PATH",
                help="your own LeRobot checkpoint as backbone NAME (repeatable; a repo id may end "
                     "in @REVISION); without --backbones the grid's backbones are these")
    g.addoption("--dataset", action="append", metavar="NAME=REPO_ID_OR_PATH",
                help="your own LeRobotDataset (v3) as suite NAME (repeatable); without --suites "
                     "the grid's suites are these")
    g.addoption("--camera-map", metavar="POLICY_CAM=DATASET_CAM,...",
                help="which dataset camera feeds each policy camera (short names: front = "
                     "observation.images.front); default: identical names, else in order")
    g.addoption("--seeds", help="comma list of ints, e.g. 0,1,2")
    g.addoption("--controls", help=f"comma list of control kinds ({','.join(control_kinds())}) or none")
    g.addoption("--steps", type=int, help="projector steps (overrides the profile's protocol)")
    g.addoption("--results-dir", help="results store (default .graftbench/results/<profile>)")
    g.addoption("--report", help="where REPORT.md goes (default: REPORT.md at the repo root)")
    g.addoption("--rerun", action="store_true", help="recompute cells that already have a record")
    g.addoption("--rollouts", type=int, default=0, metavar="N",
                help="also roll every cell out in the LIBERO simulator, N episodes per task "
                     "(needs the libero extra and a LIBERO-backed suite: --profile sim)")
    g.addoption("--sim-tasks", metavar="IDS",
                help="sim suites: the LIBERO task ids to demonstrate and roll out, e.g. 0,1,2 "
                     "(default: bench.sim.demos.DEFAULT_SPECS); a task the scripted expert "
                     "cannot solve is refused")
    g.addoption("--sim-demos", type=int, metavar="N",
                help="sim suites: successful scripted demonstrations per task (default 3)")
    g.addoption("--features", default="cache", choices=("cache", "loop"),
                help="pooled features from the on-disk cache (default) or the encoder in the loop")
    g.addoption("--feature-dtype", default="fp16", choices=("fp16", "bf16", "float32"),
                help="how the feature store keeps features on disk: fp16 (default; moves a "
                     "cell's MSE < 2e-4 relative, docs/PERFORMANCE.md), bf16, or float32 (the "
                     "encoder's numbers bit for bit, twice the disk)")
    _add_executor_options(g)
    from bench.regression.run import add_baseline_options

    add_baseline_options(parser)


def _add_executor_options(g) -> None:
    """Where cells run (bench.run.executors): here, or as one submitit job array."""
    g.addoption("--executor", default="local", choices=("local", "slurm", "submitit-local"),
                help="local (default): in this process; slurm: the selected cells as ONE Slurm "
                     "job array via submitit; submitit-local: the same on this machine")
    g.addoption("--slurm-partition", help="sbatch --partition")
    g.addoption("--slurm-time", type=int, default=240, help="minutes per cell task (sbatch --time)")
    g.addoption("--slurm-gpus-per-task", type=int, default=1, help="sbatch --gpus-per-task")
    g.addoption("--slurm-array-parallelism", type=int, default=64,
                help="array tasks running at once (sbatch --array=0-N%%P)")


def _seeds(values: tuple[str, ...] | None) -> tuple[int, ...] | None:
    if not values:
        return None
    bad = [v for v in values if not v.isdigit()]
    if bad:
        raise ValueError(f"--seeds {','.join(values)}: {bad} not a non-negative integer; give a "
                         "comma list such as --seeds 0,1,2")
    return tuple(int(v) for v in values)


def _positive(option: str, value: int | None, what: str) -> int | None:
    if value is not None and value < 1:
        raise ValueError(f"{option} {value}: give a positive number of {what} (at least 1)")
    return value


def build_profile(config: pytest.Config):
    """The run's Profile: --profile (else the --grid file's, else tiny), then the --grid file's
    values, then every grid option given on the command line."""
    opt = config.getoption
    try:
        grid = read_grid_file(opt("--grid")) if opt("--grid") else None
        base = opt("--profile") or (grid.profile if grid is not None else None)
        profile = get_profile(base or DEFAULT_PROFILE)
        if grid is not None:
            profile = grid.apply(profile)
        profile = _user_world(profile, opt)
        seeds = _csv(opt("--seeds"))
        controls = _csv(opt("--controls"))
        if controls == ("none",):
            controls = ()
        valid = control_kinds()
        bad = [c for c in controls or () if c not in valid]
        if bad:
            raise ValueError(f"--controls {opt('--controls')}: unknown control kind(s) {bad}; "
                             f"valid: {', '.join(valid)} (or none)")
        return with_overrides(
            profile,
            backbones=_csv(opt("--backbones")),
            encoders=_csv(opt("--encoders")),
            suites=_csv(opt("--suites")),
            seeds=_seeds(seeds),
            controls=controls,
            steps=_positive("--steps", opt("--steps"), "projector steps"),
            **_sim_demos(profile, opt),
        )
    except ValueError as e:
        raise pytest.UsageError(str(e)) from None


def _sim_demos(profile, opt) -> dict:
    """--sim-tasks / --sim-demos as Profile fields, refused unless the suites are simulated and
    the scripted expert solves every task (its measured success named, bench.sim.expert)."""
    tasks, demos = opt("--sim-tasks"), opt("--sim-demos")
    if tasks is None and demos is None:
        return {}
    shown = f"--sim-tasks {tasks}" if tasks is not None else f"--sim-demos {demos}"
    if profile.data_source != "sim":
        raise ValueError(f"{shown}: profile {profile.name!r} has no simulated suites; use "
                         "--profile sim")
    _positive("--sim-demos", demos, "demonstrations per task")
    ids = _csv(tasks) or ()
    if not all(t.isdigit() for t in ids):
        raise ValueError(f"--sim-tasks {tasks}: not a comma list of LIBERO task ids; give e.g. "
                         "--sim-tasks 0,1,2")
    ids = tuple(int(t) for t in ids)
    from bench.sim.expert import check_solvable

    for suite in _csv(opt("--suites")) or profile.suites:
        try:
            check_solvable(suite, ids)
        except ValueError as e:
            raise ValueError(f"--sim-tasks {tasks}: {e}") from None
    return {"sim_tasks": ids or None, "sim_demos": demos}


def _user_world(profile, opt):
    """--policy / --dataset / --camera-map on top of the grid file's (each replaces its table)."""
    from bench.grid.userworld import parse_camera_map, parse_named, with_user_world

    given = {key: opt(option) for key, option in (("policies", "--policy"), ("datasets", "--dataset"))}
    return with_user_world(
        profile,
        policies=parse_named("--policy", given["policies"]) if given["policies"] else None,
        datasets=parse_named("--dataset", given["datasets"]) if given["datasets"] else None,
        camera_map=(parse_camera_map("--camera-map", opt("--camera-map"))
                    if opt("--camera-map") else None))


FOLDED_FIELDS = ("backbones", "encoders", "suites", "seeds", "controls", "control_encoders")


def option_labels(profile, config: pytest.Config) -> dict[str, str]:
    """{profile field: where its values came from}, for messages: "--seeds 0,0" when given on
    the command line, "study.toml: seeds" when read from the grid file, else the field."""
    labels = {}
    for field in FOLDED_FIELDS:
        given = getattr(config.option, field, None) if field != "control_encoders" else None
        labels[field] = (f"--{field} {given}" if given else
                         f"{profile.grid_file.path}: {field}" if profile.grid_file else field)
    return labels


def fold_duplicates(profile, labels: dict[str, str]):
    """(the profile with each name or seed listed twice kept once, one line per fold). A cell id
    names one measurement, so `--seeds 0,0` can only mean seed 0: folded and said, not refused
    (a name given twice with two meanings, `--policy a=X --policy a=Y`, is refused instead)."""
    import dataclasses

    changes, lines = {}, []
    for field in FOLDED_FIELDS:
        values = getattr(profile, field)
        once = tuple(dict.fromkeys(values))
        if once == values:
            continue
        twice = ", ".join(str(v) for v in dict.fromkeys(v for v in values if values.count(v) > 1))
        lines.append(f"[graftbench] {labels[field]}: {twice} listed twice, folded: each cell runs "
                     f"once ({field} {','.join(map(str, once))})")
        changes[field] = once
    return dataclasses.replace(profile, **changes), lines


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


def check_startup(profile, labels: dict[str, str] | None = None) -> list[str]:
    """Every name and user path of the grid, before collection: each bad one a one-line
    UsageError (exit 4, no cell run). Returns the camera pairing lines to print. The output
    folders come after (the session opens --results-dir, then probes --report: the report
    defaults to a folder inside the results dir, whose own error names the right option)."""
    validate_names(profile, labels)
    return check_user_world(profile)


def check_executor_options(config: pytest.Config) -> None:
    """The Slurm numbers: one-line UsageErrors naming the option."""
    for option, least in (("--slurm-time", 1), ("--slurm-gpus-per-task", 0),
                          ("--slurm-array-parallelism", 1)):
        value = config.getoption(option)
        if value < least:
            raise pytest.UsageError(f"{option} {value}: give a whole number >= {least}")


def validate_names(profile, labels: dict[str, str] | None = None) -> None:
    """Unknown backbone/suite/encoder names: a UsageError naming where the name came from
    (`labels`, option_labels) and listing the valid ones. Timm names are checked on timm's
    registry and a meta-device build (< 0.5 s); a user's MODULE:FACTORY is built and probed."""
    from backbones import get_entry
    from bench.suites import SUITES
    from encoders import get_spec

    labels = labels or {}
    policies, datasets = dict(profile.policies), dict(profile.datasets)
    checks = [("backbones", b, get_entry) for b in profile.backbones if b not in policies]
    checks += [("encoders", e, lambda e: get_spec(e, profile.source)) for e in profile.encoders]
    checks += [("control_encoders", e, lambda e: get_spec(e, profile.source))
               for e in profile.control_encoders if e not in profile.encoders]
    for field, name, check in checks:
        try:
            check(name)
        except ValueError as e:
            raise pytest.UsageError(f"{labels.get(field, '--' + field)}: {e}") from None
    for s in profile.suites:
        if s not in SUITES and s not in datasets:
            raise pytest.UsageError(f"{labels.get('suites', '--suites')}: unknown suite {s!r}; "
                                    f"valid suites: {', '.join(SUITES)}")


def check_user_world(profile) -> list[str]:
    """Every --policy x --dataset pair (cameras, dims, saved stats, tasks), checked at start-up
    before any cell runs: a mismatch is a one-line UsageError (exit 4). Returns the camera
    pairing of each pair, one line each, for the terminal."""
    from bench.run.userworld import check_world
    from bench.suites.base import SuiteUnavailable

    if profile.camera_map and not profile.policies:
        given = ",".join(f"{p}={d}".replace("observation.images.", "")
                         for p, d in profile.camera_map)
        raise pytest.UsageError(f"--camera-map {given}: it maps the cameras of a --policy, and "
                                "none is given; fix: add --policy NAME=FOLDER or drop --camera-map")
    if not profile.policies and not profile.datasets:
        return []
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
    from bench.sim.env import INSTALL_HINT, libero_available

    if not libero_available():
        raise pytest.UsageError(f"--rollouts {rollouts}: the LIBERO simulator (the libero "
                                f"extra) is not installed; fix: {INSTALL_HINT}")
    if profile.data_source == "sim":
        from bench.sim.demos import demo_spec

        for suite in profile.suites:
            spec = demo_spec(suite, profile.sim_tasks, profile.sim_demos)
            # demos use init states 0.. (at most max_attempts), rollouts 49, 48, ...: disjoint
            if spec.max_attempts + rollouts > 50:
                raise pytest.UsageError(
                    f"--rollouts {rollouts}: with {spec.episodes_per_task} demonstrations per "
                    f"task (init states 0..{spec.max_attempts - 1}) rollouts would reuse a "
                    f"demonstration's init state; give --rollouts <= {50 - spec.max_attempts}")


def report_path(report: str | None, results: str | None, profile: str, results_dir: Path) -> Path:
    """Where the report goes: --report; else beside an explicit --results-dir; else the repo's
    REPORT.md for the default tiny run (the committed report), else beside the results."""
    if report:
        return Path(report)
    if results is None and profile == "tiny":
        return REPO_ROOT / "REPORT.md"
    return results_dir / "REPORT.md"


def check_writable(option: str, folder: Path) -> None:
    """A UsageError naming the option when `folder` cannot be created or written."""
    import tempfile

    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-probe-"):
            pass
    except OSError as e:
        raise pytest.UsageError(f"{option}: {folder} is not writable ({e.strerror}); "
                                "pass a writable folder") from None
