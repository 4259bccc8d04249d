"""Scripted demonstrations in real LIBERO scenes, written as a LeRobotDataset v3.

For each task, the scripted expert (bench.sim.expert) runs from LIBERO's official init states in
order (0, 1, 2, ...) until `episodes_per_task` episodes succeeded or `max_attempts` were tried;
only successful episodes are kept. Each kept frame is what a policy sees (bench.sim.env.observe:
LeRobot's preprocess_observation + LIBERO env processor, images turned 180 degrees) and the
action the expert took there, so the data matches LeRobot's public LIBERO datasets: cameras
observation.images.image / observation.images.wrist_image stored as "image" (H, W, 3) uint8,
observation.state (8: eef xyz, eef axis-angle, 2 gripper joints), action (7: OSC_POSE delta,
gripper -1 open / +1 close), 20 fps, one LIBERO instruction per episode.

Resumable: every attempt is logged to `<work>/attempts.jsonl` and every kept episode staged as
an .npz before the dataset is written, so an interrupted run continues where it stopped.
Deterministic: each attempt's env seed derives from (seed, task, init state) only.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from bench.progress import STDERR, Progress, ProgressSink, countdown, say
from bench.sim.expert import ExpertParams, ScriptedExpert, check_solvable, episode_seed
from ondisk.filelock import exclusive
from ondisk.paths import build_dataset_dir, cache_dir
from ondisk.lerobot_dataset import write_dataset
from ondisk.libero_format import ACTION_KEY, IMAGE_KEYS, STATE_KEY, libero_features

GENERATOR_VERSION = "4"  # bump when a change here (or in the expert) changes generated data
EXPERT_SUCCESS_FILE = "expert_success.json"
SUITE_FILE = "graftbench_suite.json"


@dataclass(frozen=True)
class DemoSpec:
    """What to generate. Defaults: a small suite that builds in minutes on 2 CPU cores."""

    suite: str = "spatial"
    tasks: tuple[int, ...] = (0, 1, 2, 3)  # LIBERO task ids
    episodes_per_task: int = 3  # successful episodes kept per task
    max_attempts: int = 8  # init states tried per task (0, 1, ...) before giving up
    seed: int = 0
    max_steps: int = 280  # LeRobot's LIBERO-Spatial / -Object episode limit
    image_size: int = 128  # public LeRobot LIBERO datasets: 256
    # DART-style noise injection (Laskey et al. 2017): the std of Gaussian noise added to the
    # EXECUTED translation actions (dims 0-2, action units), while the recorded label stays the
    # expert's clean action; the closed-loop expert corrects the push, so the data shows
    # recoveries from states off its own path. 0: none (and not part of the key, so the suites
    # generated before it keep theirs).
    action_noise: float = 0.0
    # The expert's speed (ExpertParams.speed, 0 < s <= 1): below 1 its translation actions stay
    # within +-s, unsaturated (a learned policy undershot saturated ones). 1: the original
    # expert, and not part of the key either.
    expert_speed: float = 1.0

    def __post_init__(self):
        check_solvable(self.suite, self.tasks)  # no demonstrations from a task it never solved
        if not 0.0 < self.expert_speed <= 1.0:
            raise ValueError(f"expert speed {self.expert_speed}: give 0 < speed <= 1 (action "
                             "units; 1 = the original expert)")
        if self.episodes_per_task < 1 or self.max_attempts < self.episodes_per_task:
            raise ValueError(f"DemoSpec needs 1 <= episodes_per_task <= max_attempts; got "
                             f"{self.episodes_per_task} and {self.max_attempts}")

    def key(self) -> str:
        """12 hex chars naming the content (generator version + every field)."""
        fields = asdict(self)
        if not self.action_noise:
            del fields["action_noise"]
        if self.expert_speed == 1.0:
            del fields["expert_speed"]
        blob = json.dumps({"version": GENERATOR_VERSION, **fields}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]


# The suites the "sim" source serves: four tasks each where the expert measured 10/10 (spatial)
# or 5/5 (object) from init states 0.. (docs/LIBERO_SIM.md).
DEFAULT_SPECS = {"spatial": DemoSpec("spatial", tasks=(0, 1, 2, 3)),
                 "object": DemoSpec("object", tasks=(0, 2, 3, 4))}


def demo_spec(suite: str, tasks: tuple[int, ...] = (), episodes: int = 0,
              action_noise: float = 0.0, expert_speed: float = 1.0) -> DemoSpec:
    """The suite's DEFAULT_SPECS entry with other task ids and demonstrations per task (empty /
    0: the default's). A few more attempts than episodes, for the odd failed init state."""
    base = DEFAULT_SPECS[suite]
    episodes = episodes or base.episodes_per_task
    return replace(base, tasks=tuple(tasks) or base.tasks, episodes_per_task=episodes,
                   max_attempts=max(base.max_attempts, episodes + 4), action_noise=action_noise,
                   expert_speed=expert_speed)


def repo_id(suite: str) -> str:
    return f"graftbench/sim_libero_{suite}"


def features(image_size: int) -> dict:
    """LeRobot feature spec: LIBERO's names, images (H, W, C) stored as "image" (not video)."""
    return libero_features(image_size)


@dataclass
class Episode:
    """One expert attempt: per-frame arrays (T, ...) and its outcome."""

    task: int
    init_state: int
    success: bool
    image: np.ndarray  # (T, H, W, 3) uint8, dataset orientation
    wrist_image: np.ndarray  # (T, H, W, 3) uint8
    state: np.ndarray  # (T, 8) float32
    action: np.ndarray  # (T, 7) float32
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def steps(self) -> int:
        return int(self.action.shape[0])


def run_expert_episode(env, suite: str, task: int, init_state: int, seed: int,
                       max_steps: int, description: str, action_noise: float = 0.0,
                       expert_speed: float = 1.0, on_step=None) -> Episode:
    """Run the scripted expert once from `init_state`, recording every observed frame (and the
    expert's clean action as its label, whatever noise is executed: DemoSpec.action_noise).
    `on_step(k)` before each step k: an attempt renders for up to a minute or two."""
    from bench.sim import env as sim_env

    start = time.perf_counter()
    obs = sim_env.reset_to(env, init_state, episode_seed(seed, task, init_state))
    expert = ScriptedExpert(suite, ExpertParams(speed=expert_speed))
    expert.reset(env)
    noise = np.random.default_rng(episode_seed(seed, task, init_state))
    images, wrists, states, actions = [], [], [], []
    success = False
    for step in range(max_steps):
        if on_step is not None:
            on_step(step)
        raw = sim_env.observe([obs], [description])
        action = expert(env)
        images.append(sim_env.to_uint8_hwc(raw[IMAGE_KEYS[0]][0]))
        wrists.append(sim_env.to_uint8_hwc(raw[IMAGE_KEYS[1]][0]))
        states.append(raw[STATE_KEY][0].numpy())
        actions.append(action.astype(np.float32))
        executed = action.astype(np.float64).copy()
        if action_noise:
            executed[:3] = np.clip(executed[:3] + noise.normal(0.0, action_noise, 3), -1, 1)
        obs, _, terminated, _, info = env.step(executed)
        if info.get("is_success", False):
            success = True
            break
    return Episode(task, init_state, success, np.stack(images), np.stack(wrists),
                   np.stack(states).astype(np.float32), np.stack(actions).astype(np.float32),
                   seconds=time.perf_counter() - start)


class _Work:
    """The resumable part: attempts log and staged episodes of one DemoSpec."""

    def __init__(self, folder: Path):
        self.folder = folder
        (folder / "episodes").mkdir(parents=True, exist_ok=True)
        self.log = folder / "attempts.jsonl"

    def attempts(self) -> dict[tuple[int, int], dict]:
        if not self.log.is_file():
            return {}
        rows = [json.loads(line) for line in self.log.read_text().splitlines() if line.strip()]
        return {(r["task"], r["init_state"]): r for r in rows}

    def episode_path(self, task: int, init_state: int) -> Path:
        return self.folder / "episodes" / f"task{task:02d}_init{init_state:02d}.npz"

    def record(self, episode: Episode) -> None:
        if episode.success:  # stage first, then log: a logged success always has its data
            path = self.episode_path(episode.task, episode.init_state)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez_compressed(tmp, image=episode.image, wrist_image=episode.wrist_image,
                                state=episode.state, action=episode.action)
            tmp.replace(path)
        row = {"task": episode.task, "init_state": episode.init_state,
               "success": episode.success, "steps": episode.steps,
               "seconds": round(episode.seconds, 2)}
        with self.log.open("a") as f:
            f.write(json.dumps(row) + "\n")

    def load(self, task: int, init_state: int) -> dict[str, np.ndarray]:
        with np.load(self.episode_path(task, init_state)) as data:
            return {k: data[k] for k in data.files}


def run_attempts(spec: DemoSpec, work: _Work, progress: ProgressSink) -> dict[tuple[int, int], dict]:
    """Run (or resume) the expert attempts of `spec`; returns the attempts log by (task, init).
    A line per attempt (10-90 s each; every 30 s inside one): the demonstrations kept of all the
    suite needs, and the time left at this run's mean rate per kept one."""
    import torch

    from bench.sim import env as sim_env

    torch.set_num_threads(1)
    render = sim_env.RenderSettings(image_size=spec.image_size)
    descriptions = sim_env.task_descriptions(spec.suite)
    done = work.attempts()
    needed = len(spec.tasks) * spec.episodes_per_task
    resumed = _kept(done, spec)
    say(progress, f"sim demos: {spec.suite}: rendering {needed - resumed} scripted demonstrations "
                  f"({len(spec.tasks)} tasks x {spec.episodes_per_task}"
                  f"{f', {resumed} resumed' if resumed else ''}; a line per attempt)")
    start = time.monotonic()
    for task in spec.tasks:
        env = None
        kept = sum(1 for (t, _), r in done.items() if t == task and r["success"])
        for init_state in range(spec.max_attempts):
            if kept >= spec.episodes_per_task:
                break
            if (task, init_state) in done:
                continue
            if env is None:  # a minute or so under load: say so before it starts
                say(progress, f"sim demos: {spec.suite} task {task}: building its scene")
                env = sim_env.make_env(spec.suite, task, render, max_steps=spec.max_steps)
            within = Progress(f"sim demos: {spec.suite} task {task} init {init_state}: step",
                              spec.max_steps, progress)  # a line every 30 s inside an attempt
            episode = run_expert_episode(env, spec.suite, task, init_state, spec.seed,
                                         spec.max_steps, descriptions[task], spec.action_noise,
                                         spec.expert_speed, on_step=within.update)
            work.record(episode)
            done[(task, init_state)] = {"success": episode.success, "steps": episode.steps}
            kept += int(episode.success)
            say(progress, f"sim demos: {spec.suite} task {task} init {init_state}: "
                          f"{'success' if episode.success else 'failure'} in {episode.steps} "
                          f"steps ({episode.seconds:.1f} s); kept {kept}/{spec.episodes_per_task}"
                          f"; suite {countdown(start, _kept(done, spec), needed, resumed)}")
        if env is not None:
            env.close()
    return work.attempts()


def _kept(attempts: dict[tuple[int, int], dict], spec: DemoSpec) -> int:
    """Demonstrations kept so far, over all tasks (at most episodes_per_task a task)."""
    return sum(min(spec.episodes_per_task,
                   sum(1 for (t, _), r in attempts.items() if t == task and r["success"]))
               for task in spec.tasks)


def expert_success(spec: DemoSpec, attempts: dict[tuple[int, int], dict]) -> dict:
    """Per-task expert success over the attempts made (what generation measured)."""
    per_task = {}
    for task in spec.tasks:
        rows = [r for (t, _), r in sorted(attempts.items()) if t == task]
        wins = [r for r in rows if r["success"]]
        per_task[str(task)] = {
            "attempts": len(rows), "successes": len(wins),
            "success_rate": len(wins) / len(rows) if rows else None,
            "init_states_kept": [r["init_state"] for r in wins][: spec.episodes_per_task],
            "median_steps_success": float(np.median([r["steps"] for r in wins])) if wins else None,
            "mean_seconds": float(np.mean([r.get("seconds", 0.0) for r in rows])) if rows else None,
        }
    return per_task


def write_suite(spec: DemoSpec, work: _Work, attempts: dict, root: Path,
                progress: ProgressSink) -> Path:
    """The kept episodes of `spec` as a LeRobotDataset at `root` (must not exist), written by the
    one writer (ondisk.lerobot_dataset), then the suite's own files: how it was generated and
    the expert's measured success."""
    from bench.sim import env as sim_env

    say(progress, f"sim demos: {spec.suite}: writing the kept episodes as a LeRobotDataset")
    descriptions = sim_env.task_descriptions(spec.suite)
    per_task = expert_success(spec, attempts)

    def stream():
        for task in spec.tasks:
            for init_state in per_task[str(task)]["init_states_kept"]:
                data = work.load(task, init_state)
                yield descriptions[task], (
                    {IMAGE_KEYS[0]: data["image"][i], IMAGE_KEYS[1]: data["wrist_image"][i],
                     STATE_KEY: data["state"][i], ACTION_KEY: data["action"][i]}
                    for i in range(data["action"].shape[0]))

    write_dataset(root, repo_id(spec.suite), features(spec.image_size), "panda",
                  sim_env.CONTROL_HZ, stream())
    episodes = [{"task": task, "init_state": init}
                for task in spec.tasks for init in per_task[str(task)]["init_states_kept"]]
    (root / SUITE_FILE).write_text(json.dumps({
        "name": spec.suite, "source": "sim", "generator_version": GENERATOR_VERSION,
        **asdict(spec), "render": sim_env.RenderSettings(image_size=spec.image_size).as_dict(),
        "libero_task_ids": list(spec.tasks), "episodes": episodes,
    }, indent=1))
    (root / EXPERT_SUCCESS_FILE).write_text(json.dumps(per_task, indent=1))
    return root


def generate(spec: DemoSpec, root: str | Path | None, progress: ProgressSink) -> Path:
    """Generate (or resume, or reuse) the demonstration suite of `spec` (None `root`: in the
    cache); returns its folder. `progress` is required: a session's own sink, or STDERR from
    the command line; a default of stderr would be captured by pytest, and silent."""
    final = Path(root) if root is not None else suite_path(spec)
    if (final / "meta" / "info.json").is_file():
        return final
    # Two runs sharing a cache: one renders, the other waits and reuses its suite (unlocked, both
    # ran the same attempts into one work folder).
    with exclusive(final.parent / f"{final.name}.lock"):
        if (final / "meta" / "info.json").is_file():
            return final
        work = _Work(final.parent / f"{final.name}.work")
        attempts = run_attempts(spec, work, progress)
        short = {t: r["successes"] for t, r in expert_success(spec, attempts).items()
                 if r["successes"] < spec.episodes_per_task}
        if short:
            say(progress, f"sim demos: fewer than {spec.episodes_per_task} successes for tasks "
                          f"{short} within {spec.max_attempts} attempts")
        return build_dataset_dir(final, lambda tmp: write_suite(spec, work, attempts, tmp,
                                                                progress))


def suite_path(spec: DemoSpec) -> Path:
    """Where the dataset of `spec` lives (cache dir, keyed on its content)."""
    return cache_dir() / "sim_suites" / f"{spec.suite}-{spec.key()}"


def suite_info(root: str | Path) -> dict:
    """graftbench_suite.json of a generated suite (spec, render settings, LIBERO task ids)."""
    return json.loads((Path(root) / SUITE_FILE).read_text())


def libero_task_ids(root: str | Path) -> list[int]:
    """LIBERO task id of each dataset task_index of a generated suite (index = task_index)."""
    return [int(t) for t in suite_info(root)["libero_task_ids"]]


def render_settings(root: str | Path):
    """The RenderSettings a generated suite was rendered with (use the same for rollouts)."""
    from bench.sim.env import RenderSettings

    return RenderSettings(**suite_info(root)["render"])


def _parse_main(argv: list[str] | None):
    """(DemoSpec, --root) from the command line, every input and the simulator checked before
    any env is built: bad input is one line naming the option and the fix, exit 4 (the usage
    error of every entry point, bench.option_values)."""
    from bench.option_values import CommandParser, refuse, whole_at_least

    prog = "python -m bench.sim.demos"
    parser = CommandParser(prog=prog, description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="spatial", choices=["spatial", "object"])
    parser.add_argument("--tasks", default=None, help="LIBERO task ids, e.g. 0,1,2 "
                        "(default: the suite's DEFAULT_SPECS entry)")
    parser.add_argument("--episodes", type=whole_at_least(1, "3"), default=None)
    parser.add_argument("--max-attempts", type=whole_at_least(1, "10"), default=None)
    parser.add_argument("--seed", type=whole_at_least(0, "0"), default=None)
    parser.add_argument("--image-size", type=whole_at_least(16, "128"), default=None)
    parser.add_argument("--root", default=None, help="output folder (default: the cache)")
    args = parser.parse_args(argv)
    base = DEFAULT_SPECS[args.suite]
    if args.tasks is not None and not all(t.strip().isdigit() for t in args.tasks.split(",")):
        refuse(prog, f"--tasks {args.tasks!r}: not a comma list of LIBERO task ids; give e.g. "
                     "--tasks 0,1,2")
    tasks = tuple(int(t) for t in args.tasks.split(",")) if args.tasks else base.tasks
    try:
        check_solvable(args.suite, tasks)
    except ValueError as e:
        refuse(prog, f"--tasks {args.tasks or ','.join(map(str, tasks))}: {e}")
    episodes = base.episodes_per_task if args.episodes is None else args.episodes
    attempts = base.max_attempts if args.max_attempts is None else args.max_attempts
    try:
        spec = DemoSpec(args.suite, tasks, episodes, attempts,
                        base.seed if args.seed is None else args.seed, base.max_steps,
                        base.image_size if args.image_size is None else args.image_size)
    except ValueError as e:  # one line naming the options, before any env is built
        refuse(prog, f"--episodes {episodes} --max-attempts {attempts}: {e}; give "
                     "--max-attempts at least --episodes")
    if args.root is not None and Path(args.root).exists() and not Path(args.root).is_dir():
        refuse(prog, f"--root {args.root}: a file, not a folder; give a folder for the suites")
    from bench.sim.env import INSTALL_HINT, libero_available

    if not libero_available():
        refuse(prog, f"the LIBERO simulator (the libero extra) is not installed; fix: "
                     f"{INSTALL_HINT}")
    return spec, args.root


def main(argv: list[str] | None = None) -> None:
    """python -m bench.sim.demos [--suite spatial|object] [--tasks 0,1,2,3] [--episodes 3] ..."""
    spec, root = _parse_main(argv)
    path = generate(spec, root, STDERR)
    print(path)
    print((path / EXPERT_SUCCESS_FILE).read_text())


if __name__ == "__main__":
    main()
