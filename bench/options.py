"""The grid's command-line options: declared, parsed ONCE into a frozen `RunOptions` (the
profile, where results and the report go, how cells run, the regression and screen options),
each bad value a one-line `pytest.UsageError` naming the option (never an INTERNALERROR). The
session passes `RunOptions` down; nothing reads the config's options after. The names and paths
the options give are checked next: bench.startup."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from bench.grid.gridfile import read_grid_file
from ondisk.paths import REPO_ROOT
from bench.grid.kinds import control_kinds
from bench.grid.protocol import Profile, get_profile, with_overrides
from bench.robust.cases import add_robustness_option, with_robustness
from bench.screen.proxies import PROXIES, proxy_names
from bench.screen.selection import (DEFAULT_SCREEN_BY, REFERENCES, SHORT, ScreenOptions,
                                    parse_screen_by, parse_screen_keep)
from bench.option_values import (control_list, listed, pack_grafts, positive, protocol_value,
                                 refuse_empty, report_file, seeds, typed_options)
from bench.sim.batching import IN_PROCESS, Batching
from bench.startup import (check_environment, check_rollout_batch, check_rollout_workers,
                           check_rollouts_possible, check_sim_suites_possible)

DEFAULT_PROFILE = "tiny"


def pytest_addoption(parser: pytest.Parser) -> None:
    g = parser.getgroup("graftbench", "graftbench grid")
    g.addoption("--profile",
                help="tiny (offline default, 14 cells; --seeds 0,1: 28), tiny-full (136 cells), paper, sim")
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
    # Numbers and choices are declared untyped: bench.option_values.typed_options checks them,
    # one line with the fix instead of argparse's usage block.
    g.addoption("--steps", metavar="N", help="projector steps (overrides the profile's protocol)")
    g.addoption("--results-dir", help="results store (default .graftbench/results/<profile>)")
    g.addoption("--report", help="where REPORT.md goes (default: REPORT.md in --results-dir when "
                                 "given; else at the repo root for --profile tiny, else in the "
                                 "profile's results dir)")
    g.addoption("--replace-report", action="store_true",
                help="let the report replace one that holds more cells than it will (bench.outputs)")
    g.addoption("--rerun", action="store_true", help="recompute cells that already have a record")
    g.addoption("--features", default="cache", metavar="cache|loop",
                help="pooled features from the on-disk cache (default) or the encoder in the loop")
    g.addoption("--feature-dtype", default="fp16", metavar="fp16|bf16|float32",
                help="how the feature store keeps features on disk: fp16 (default; moves a "
                     "cell's MSE < 2e-4 relative, docs/PERFORMANCE.md), bf16, or float32 (the "
                     "encoder's numbers bit for bit, twice the disk)")
    _add_sim_options(g)
    _add_screen_options(g)
    add_robustness_option(g)  # the robustness tier (bench.robust.cases)
    _add_executor_options(g)
    from bench.regression.run import add_baseline_options

    add_baseline_options(parser)


def _add_sim_options(g) -> None:
    """Closed-loop rollouts and the scripted demonstrations of the sim profile (bench.sim)."""
    g.addoption("--rollouts", default=0, metavar="N",
                help="also roll every cell out in the LIBERO simulator, N episodes per task "
                     "(needs the libero extra and a LIBERO-backed suite: --profile sim)")
    g.addoption("--rollout-batch", default=1, metavar="B",
                help="envs of a task rolled out at once, one batched policy call per step "
                     "(LeRobot's gym vector env; default 1: one env in-process, the faster on "
                     "2 CPU cores, docs/PERFORMANCE.md)")
    g.addoption("--rollout-workers", default=1, metavar="W", help="processes stepping the "
                "simulator, same rows (default 1; 2 on 2 cores: docs/PERFORMANCE.md)")
    g.addoption("--rollout-envs", default="sync", metavar="sync|async",
                help="with --rollout-batch > 1: the B envs in this process (sync) or one worker "
                     "process and render context each (async, as lerobot-eval)")
    g.addoption("--sim-tasks", metavar="IDS",
                help="sim suites: the LIBERO task ids to demonstrate and roll out, e.g. 0,1,2 "
                     "(default: bench.sim.demos.DEFAULT_SPECS); a task the scripted expert "
                     "cannot solve is refused")
    g.addoption("--sim-demos", metavar="N",
                help="sim suites: successful scripted demonstrations per task (default 3)")
    g.addoption("--sim-demo-noise", metavar="SIGMA",
                help="sim suites: std of Gaussian noise on the executed translation actions of "
                     "the scripted demonstrations, labels kept clean (DART; default 0)")
    g.addoption("--sim-demo-speed", metavar="S",
                help="sim suites: the scripted expert's speed, 0 < S <= 1: its translation "
                     "actions within +-S, unsaturated (default 1: the original expert)")


def _add_screen_options(g) -> None:
    """The screen tier (bench.screen): screen every encoder, graft the best few. The proxies
    named are the table's (bench.screen.proxies) when the plugin loads."""
    g.addoption("--screen", action="store_true",
                help="screen every --encoders name first (no training: "
                     f"{', '.join(p.label for p in PROXIES.values())} on stored features; cases "
                     "test_screen[BACKBONE-SUITE-ENCODER]), then graft only the best "
                     "--screen-keep plus the pixels/blind references")
    g.addoption("--screen-keep", metavar="K|all",
                help=f"with --screen: encoders grafted per backbone x suite (default "
                     f"{DEFAULT_SCREEN_KEEP}); all: every screened one (the calibration study)")
    g.addoption("--screen-by", metavar="PROXY",
                help=f"with --screen: the proxy that ranks them, {_proxy_choices()}, or short "
                     "(the 1/4-steps short graft's MSE, lower is better: the selection then waits "
                     "for every short graft)")
    g.addoption("--screen-calibration", metavar="RESULTS_DIR",
                help="with --screen: the results dir of a calibration study (a --screen "
                     "--screen-keep all run) whose agreement with the graft the report quotes "
                     "beside this run's selection")


DEFAULT_SCREEN_KEEP = 3


def _proxy_choices() -> str:
    """'logme (default), ridge, knn, entropy': the table's proxies, the default marked."""
    return ", ".join(p + (" (default)" if p == DEFAULT_SCREEN_BY else "") for p in proxy_names())


def screen_options(config: pytest.Config, profile):
    """(the profile with the references added to its encoders, the run's ScreenOptions or None,
    lines to print): --screen, --screen-keep, --screen-by checked, each bad one a UsageError."""
    keep, by = config.getoption("--screen-keep"), config.getoption("--screen-by")
    calibration = config.getoption("--screen-calibration")
    if not config.getoption("--screen"):
        given = [(o, v) for o, v in (("--screen-keep", keep), ("--screen-by", by),
                                     ("--screen-calibration", calibration)) if v is not None]
        if given:
            option, value = given[0]
            raise pytest.UsageError(f"{option} {value}: it chooses what a screen keeps, and "
                                    f"--screen is not given; fix: add --screen or drop {option}")
        return profile, None, []
    import dataclasses

    try:
        options = ScreenOptions(parse_screen_keep(keep) if keep is not None else DEFAULT_SCREEN_KEEP,
                                parse_screen_by(by) if by is not None else DEFAULT_SCREEN_BY,
                                _calibration(calibration) if calibration is not None else None)
    except ValueError as e:
        raise pytest.UsageError(str(e)) from None
    executor = config.getoption("--executor")
    if options.by == SHORT and executor != "local":
        # The job array is submitted from the selection, which would wait on short grafts that
        # are themselves in the array: not supported yet.
        raise pytest.UsageError(f"--screen-by short with --executor {executor}: the selection "
                                "waits for short grafts run in this process; fix: --executor "
                                f"local, or rank by a proxy ({', '.join(proxy_names())})")
    added = tuple(r for r in REFERENCES if r not in profile.encoders)
    screened = [e for e in profile.encoders if e not in REFERENCES]
    # The references are screened too (every listed encoder is): count what will run.
    pairs = len(profile.backbones) * len(profile.suites)
    listed_n = len(screened) + len(REFERENCES)
    lines = [f"[graftbench] --screen: {listed_n} encoder(s) screened on each of {pairs} backbone "
             f"x suite ({listed_n * pairs} screens, the references {', '.join(REFERENCES)} "
             f"included" + (", added to --encoders" if added else "") + f"); grafted: the best "
             f"{options.keep or 'all'} of the {len(screened)} listed by {options.by}, and the "
             "references"]
    if options.keep is not None and options.keep > len(screened):
        lines.append(f"[graftbench] --screen-keep {options.keep} is more than the "
                     f"{len(screened)} listed encoder(s) (references aside): all are grafted")
    return (dataclasses.replace(profile, encoders=profile.encoders + added), options, lines)


def _calibration(value: str) -> str:
    """--screen-calibration's folder, absolute (the selection stores it for the report), once
    bench.results.store.load_calibration finds a calibration study there."""
    from bench.results.store import load_calibration

    try:
        load_calibration(value)
    except ValueError as e:
        raise ValueError(f"--screen-calibration {value}: {e}; fix: name the --results-dir of a "
                         "`pytest bench --screen --screen-keep all` run, or drop the option") from None
    return str(Path(value).resolve())


def _add_executor_options(g) -> None:
    """Where cells run (bench.cell.executors): here, or as one submitit job array."""
    g.addoption("--executor", default="local", metavar="local|slurm|submitit-local",
                help="local (default): in this process; slurm: the selected cells as ONE Slurm "
                     "job array via submitit; submitit-local: the same on this machine")
    g.addoption("--slurm-partition", help="sbatch --partition")
    g.addoption("--slurm-time", default=240, help="minutes per cell task (sbatch --time)")
    g.addoption("--slurm-gpus-per-task", default=1, help="sbatch --gpus-per-task")
    g.addoption("--slurm-array-parallelism", default=64,
                help="array tasks running at once (sbatch --array=0-N%%P)")
    g.addoption("--pack-grafts", metavar="K", help="train up to K graft cells of one backbone x "
                "suite through one frozen-backbone pass, each its own record (default 1: one at "
                "a time; grid-file key pack_grafts; --executor local only)")


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
        controls = control_list(opt("--controls"))
        return with_overrides(
            profile,
            backbones=listed("--backbones", opt("--backbones")),
            encoders=listed("--encoders", opt("--encoders")),
            suites=listed("--suites", opt("--suites")),
            seeds=seeds(listed("--seeds", opt("--seeds"))),
            controls=controls,
            steps=protocol_value("--steps", "steps", opt("--steps")),
            **_sim_demos(profile, opt),
        )
    except ValueError as e:
        raise pytest.UsageError(str(e)) from None


def _sim_demos(profile, opt) -> dict:
    """--sim-tasks / --sim-demos as Profile fields, refused unless the suites are simulated and
    the scripted expert solves every task (its measured success named, bench.sim.expert)."""
    tasks, demos, noise = opt("--sim-tasks"), opt("--sim-demos"), opt("--sim-demo-noise")
    speed = opt("--sim-demo-speed")
    given = [f"{name} {value}" for name, value in (("--sim-tasks", tasks), ("--sim-demos", demos),
             ("--sim-demo-noise", noise), ("--sim-demo-speed", speed)) if value is not None]
    if not given:
        return {}
    shown = given[0]
    if profile.data_source != "sim":
        raise ValueError(f"{shown}: profile {profile.name!r} has no simulated suites; use "
                         "--profile sim")
    positive("--sim-demos", demos, "demonstrations per task")
    ids = listed("--sim-tasks", tasks) or ()
    if not all(t.isdigit() for t in ids):
        raise ValueError(f"--sim-tasks {tasks}: not a comma list of LIBERO task ids; give e.g. "
                         "--sim-tasks 0,1,2")
    ids = tuple(int(t) for t in ids)
    from bench.sim.expert import check_solvable

    for suite in listed("--suites", opt("--suites")) or profile.suites:
        try:
            check_solvable(suite, ids)
        except ValueError as e:
            raise ValueError(f"--sim-tasks {tasks}: {e}") from None
    if noise is not None and not 0.0 <= noise <= 1.0:
        raise ValueError(f"--sim-demo-noise {noise}: give a std in action units, 0 to 1")
    if speed is not None and not 0.0 < speed <= 1.0:
        raise ValueError(f"--sim-demo-speed {speed}: give the expert's largest translation "
                         "action, 0 < S <= 1 (1: the original expert)")
    return {"sim_tasks": ids or None, "sim_demos": demos, "sim_demo_noise": noise,
            "sim_demo_speed": speed}


def _user_world(profile, opt):
    """--policy / --dataset / --camera-map on top of the grid file's (each replaces its table)."""
    from bench.grid.user_specs import parse_camera_map, parse_named, with_user_world

    given = {key: opt(option) for key, option in (("policies", "--policy"), ("datasets", "--dataset"))}
    return with_user_world(
        profile,
        policies=parse_named("--policy", given["policies"]) if given["policies"] else None,
        datasets=parse_named("--dataset", given["datasets"]) if given["datasets"] else None,
        camera_map=(parse_camera_map("--camera-map", opt("--camera-map"))
                    if opt("--camera-map") is not None else None))


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


def check_executor_options(config: pytest.Config) -> None:
    """The Slurm numbers: one-line UsageErrors naming the option."""
    for option, least in (("--slurm-time", 1), ("--slurm-gpus-per-task", 0),
                          ("--slurm-array-parallelism", 1)):
        value = config.getoption(option)
        if value < least:
            raise pytest.UsageError(f"{option} {value}: give a whole number >= {least}")


def report_path(report: str | None, results: str | None, profile: str, results_dir: Path) -> Path:
    """Where the report goes: --report; else beside an explicit --results-dir; else the repo's
    REPORT.md for the default tiny run (the committed report), else beside the results."""
    if report is not None:
        return report_file(report)
    if results is None and profile == "tiny":
        return REPO_ROOT / "REPORT.md"
    return results_dir / "REPORT.md"


@dataclass(frozen=True)
class RunOptions:
    """One grid run's command line, parsed and checked (`parse_options`)."""

    profile: Profile  # duplicates folded (startup_lines say so)
    labels: dict  # {profile field: where its values came from} (option_labels)
    startup_lines: tuple[str, ...]
    results_dir: Path
    report_path: Path
    rerun: bool = False
    features_mode: str = "cache"
    feature_dtype: str = "fp16"
    rollouts: int = 0
    # --rollout-batch (envs per task at once), --rollout-envs (sync or async), --rollout-workers
    rollout_batching: Batching = IN_PROCESS
    executor: str = "local"
    slurm: object = None  # bench.cell.executors.SlurmOptions
    baseline: object = None  # bench.regression.run.BaselineOptions
    screen: object = None  # bench.screen.selection.ScreenOptions; None without --screen
    pack_grafts: int = 1  # graft cells per backbone pass (bench.cell.pack_run); 1: unpacked
    replace_report: bool = False  # --replace-report: a report with fewer cells may replace one


def parse_options(config: pytest.Config) -> RunOptions:
    """Every option of the grid, parsed and checked: a bad one is a UsageError (exit 4). Names
    and user paths are checked after (check_startup: only when the grid is collected)."""
    from bench.regression.run import BaselineOptions
    from bench.cell.executors import SlurmOptions

    opt = config.getoption
    refuse_empty(config)
    typed_options(config)  # numbers converted, choices checked: the rest reads them typed
    check_environment(config)  # before any name is built or folder written
    profile = build_profile(config)
    profile = with_robustness(profile, opt("--robustness"))  # checked: exit 4 if bad
    labels = option_labels(profile, config)
    profile, lines = fold_duplicates(profile, labels)
    profile, screen, screen_lines = screen_options(config, profile)
    results = opt("--results-dir")
    results_dir = (Path(results) if results
                   else REPO_ROOT / ".graftbench" / "results" / profile.name)
    rollouts = int(opt("--rollouts") or 0)
    if rollouts < 0:
        raise pytest.UsageError(f"--rollouts {rollouts}: give episodes per task >= 0")
    if rollouts:
        check_rollouts_possible(profile, rollouts)
    check_sim_suites_possible(profile, f"--profile {opt('--profile')}" if opt("--profile")
                              else f"{opt('--grid')}: profile {profile.name}")
    rollout_batch = check_rollout_batch(opt("--rollout-batch"), rollouts)
    check_executor_options(config)
    slurm = SlurmOptions(partition=opt("--slurm-partition"), time_min=opt("--slurm-time"),
                         gpus_per_task=opt("--slurm-gpus-per-task"),
                         array_parallelism=opt("--slurm-array-parallelism"))
    return RunOptions(
        profile, labels, tuple(lines + screen_lines), results_dir,
        report_path(opt("--report"), results, profile.name, results_dir),
        rerun=bool(opt("--rerun")), features_mode=opt("--features"),
        feature_dtype=opt("--feature-dtype"), rollouts=rollouts,
        rollout_batching=Batching(rollout_batch, opt("--rollout-envs"), check_rollout_workers(
            opt("--rollout-workers"), rollouts, rollout_batch)), executor=opt("--executor"),
        slurm=slurm, baseline=BaselineOptions.parse(config, opt("--executor")), screen=screen,
        pack_grafts=pack_grafts(opt("--pack-grafts"), profile.grid_file, opt("--executor")),
        # The default report (no --report) is the run's own output, not a file the user named:
        # a -k slice on a fresh clone replaces it, as the README's usage shows. A named report
        # keeps the fewer-cells rule; every report keeps the rest of bench.outputs' rule.
        replace_report=bool(opt("--replace-report")) or opt("--report") is None)
