"""Closed-loop rollouts of any policy in LIBERO scenes through LeRobot's LiberoEnv.

`run_rollouts(act, spec)` runs `spec.episodes_per_task` episodes per task. Init states and env
seeds are a function of the spec alone, so every caller with the same spec (every cell of a
grid) meets the same scenes: paired comparisons. `act` sees exactly what the demonstrations
store (bench.sim.env.observe) and answers an action chunk in raw units; the first
`n_action_steps` actions are executed before it is asked again (LeRobot's action-queue
semantics). An episode succeeds when LIBERO's goal predicate holds (LiberoEnv's is_success).

Init states: episode e of a task uses official init state `n - 1 - e` (n = 50: counted from
the end), while the demonstrations use them from the start (0, 1, ...): the two sets are
disjoint as long as demos + rollouts per task <= 50.

Resumable per episode: `finished` episodes (from a killed run) are kept, not rerun, and
`on_episode` is handed each new one as it ends (bench.cell.rollouts persists it through the
results store). An exception inside an episode (the env, or the policy) becomes RolloutCrashed
naming the task, episode and init state: that cell fails with it, the run goes on.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch

from bench.progress import ProgressSink, as_sink, countdown
from bench.sim import env as sim_env
from bench.sim.batching import IN_PROCESS, Batching
from bench.sim.episode import (ActFn, episode_row, execute_chunk, next_actions,
                               reads_nothing, rollout_init_state)
from bench.stats import wilson_interval


class RolloutCrashed(RuntimeError):
    """An episode raised (env or policy): the cell fails with this one line."""


@dataclass(frozen=True)
class Scenes:
    """The simulator calls the rollout loop makes: LIBERO's (bench.sim.env) by default. A test
    passes its own to drive the same loop without the simulator; nothing else differs."""

    make_env: Callable  # (suite, task, render, max_steps=) -> env with .step(action), .close()
    descriptions: Callable[[str], list[str]]  # suite -> instruction per task id
    num_init_states: Callable  # env -> int
    reset_to: Callable  # (env, init_state, env_seed) -> raw observation
    observe: Callable  # ([raw observation], [instruction]) -> what `act` receives
    # (env, steps or None): the observation `steps` steps from now is the next one read, so
    # only its frames need rendering (bench.sim.frames); a test's scenes may ignore it.
    read_after: Callable = reads_nothing


LIBERO = Scenes(sim_env.make_rollout_env, sim_env.task_descriptions, sim_env.num_init_states,
                sim_env.reset_to, sim_env.observe, sim_env.read_after)


@dataclass(frozen=True)
class RolloutSpec:
    suite: str  # "spatial" | "object"
    tasks: tuple[int, ...]  # LIBERO task ids
    episodes_per_task: int
    seed: int
    max_steps: int  # control steps per episode (LeRobot: 280 for spatial and object)
    n_action_steps: int  # chunk steps executed before re-planning

    def __post_init__(self):
        if self.suite not in sim_env.LIBERO_SUITES:
            raise ValueError(f"RolloutSpec.suite={self.suite!r}; choose one of "
                             f"{sorted(sim_env.LIBERO_SUITES)}")
        if self.episodes_per_task < 1 or self.max_steps < 1 or self.n_action_steps < 1:
            raise ValueError(f"RolloutSpec needs episodes_per_task, max_steps, n_action_steps >= 1;"
                             f" got {self.episodes_per_task}, {self.max_steps}, "
                             f"{self.n_action_steps}")


def rollout_env_seed(seed: int, task: int, episode: int) -> int:
    digest = hashlib.sha256(f"rollout:{seed}:{task}:{episode}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def progress_line(progress, spec, row: dict, count: str = "") -> None:
    """One line per finished episode, through the progress sink: inside `pytest bench` a bare
    stderr print is captured until the test ends, i.e. after the last episode. `count`: how far
    the rollouts are (bench.progress.countdown)."""
    sink = as_sink(progress)
    if sink is not None:
        sink.line(f"[rollout] {spec.suite} task {row['task']} episode {row['episode']} "
                  f"(init {row['init_state']}): {'success' if row['success'] else 'failure'} in "
                  f"{row['steps']} steps ({row['seconds']:.1f} s)"
                  + (f"; episodes {count}" if count else ""))


def episode_reporter(progress, spec, resumed: int) -> Callable[[dict], None]:
    """`report(row)` for each episode this run finishes: its line, with the episodes done of
    the spec's and the time left at this run's mean rate (resumed episodes are not timed)."""
    total, start, done = len(spec.tasks) * spec.episodes_per_task, time.monotonic(), [resumed]

    def report(row: dict) -> None:
        done[0] += 1
        progress_line(progress, spec, row, countdown(start, done[0], total, resumed))

    return report


def run_episode(act: ActFn, env, init_state: int, env_seed: int, max_steps: int,
                n_action_steps: int, description: str, scenes: Scenes = LIBERO) -> dict:
    """One closed-loop episode from `init_state`; {"init_state", "success", "steps", "seconds"}."""
    start = time.perf_counter()
    obs = scenes.reset_to(env, init_state, env_seed)
    on_reset = getattr(act, "on_reset", None)
    if on_reset is not None:  # privileged policies (the scripted expert) read the sim state
        on_reset([env])
    success, steps = False, 0
    while steps < max_steps and not success:
        actions = next_actions(act, scenes.observe([obs], [description]), n_action_steps)
        obs, done, success = execute_chunk(env, actions, max_steps - steps, scenes.read_after)
        steps += done
    return episode_row(init_state, success, steps, start)


def run_rollouts(act: ActFn, spec: RolloutSpec, progress: ProgressSink,
                 render: sim_env.RenderSettings | None = None, *, finished: list[dict] = (),
                 on_episode: Callable[[dict], None] | None = None,
                 scenes: Scenes = LIBERO, batching: Batching = IN_PROCESS,
                 vector_scenes=None) -> dict:
    """Run `spec` with policy `act`; per-episode successes, rates and Wilson 95% intervals.

    act(raw) -> (B, T, 7) raw actions, raw = {"observation.images.image": (B, 3, H, W) float32
    [0, 1], "observation.images.wrist_image": same, "observation.state": (B, 8) float32,
    "task": list[str]}. `batching` (Batching): one env in-process (`scenes`), or that many envs
    of a task in a gym vector env (`vector_scenes` LIBERO's unless a test passes its own), same
    episodes and rows.
    finished: episode rows of an interrupted run of the same policy and spec (kept, not rerun);
    on_episode: called with each new row as soon as its episode ends.
    """
    render = render or sim_env.RenderSettings()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # 2 shared cores: one thread each for sim and policy is faster
    start = time.perf_counter()
    resumed = len({(e["task"], e["episode"]) for e in finished})
    try:
        episodes = _run_all(act, spec, episode_reporter(progress, spec, resumed), render,
                            finished, on_episode, scenes, batching, vector_scenes)
    finally:
        torch.set_num_threads(threads)
    out = summarise(episodes, spec, render, time.perf_counter() - start, resumed=resumed)
    out["settings"].update(batch=batching.size, env_mode=batching.label)
    return out


def _run_all(act: ActFn, spec: RolloutSpec, report: Callable[[dict], None],
             render: sim_env.RenderSettings,
             finished, on_episode, scenes: Scenes, batching: Batching = IN_PROCESS,
             vector_scenes=None) -> list[dict]:
    done = {(int(e["task"]), int(e["episode"])): e for e in finished}
    descriptions = scenes.descriptions(spec.suite)
    episodes = []

    def kept() -> str:  # what a crash leaves for the rerun
        return (f"{len(episodes)} episode(s) finished before it are kept; rerun to resume"
                if on_episode is not None else "no episode log: a rerun starts over")

    if batching.workers > 1:
        return _run_on_workers(act, spec, report, render, done, on_episode, batching.workers,
                               scenes, descriptions, episodes, kept)
    if batching.size > 1:
        return _run_batched(act, spec, report, render, done, on_episode, batching,
                            vector_scenes, descriptions, episodes, kept)

    for task in spec.tasks:
        todo = [e for e in range(spec.episodes_per_task) if (task, e) not in done]
        env = _crash_named(lambda: scenes.make_env(spec.suite, task, render,
                                                   max_steps=spec.max_steps),
                           f"{spec.suite} task {task}: building its env", kept()) \
            if todo else None
        try:
            for episode in range(spec.episodes_per_task):
                if episode not in todo:
                    episodes.append(done[(task, episode)])
                    continue
                init_state = rollout_init_state(episode, scenes.num_init_states(env))
                row = {"task": task, "episode": episode, **_crash_named(
                    lambda: run_episode(act, env, init_state,
                                        rollout_env_seed(spec.seed, task, episode),
                                        spec.max_steps, spec.n_action_steps,
                                        descriptions[task], scenes),
                    f"{spec.suite} task {task} episode {episode} (init state {init_state})",
                    kept())}
                if on_episode is not None:
                    on_episode(row)
                episodes.append(row)
                report(row)
        finally:
            if env is not None:
                env.close()
    return episodes


def _run_batched(act: ActFn, spec: RolloutSpec, report: Callable[[dict], None], render,
                 done: dict, on_episode,
                 batching: Batching, vector_scenes, descriptions, episodes: list,
                 kept: Callable[[], str]) -> list[dict]:
    """_run_all's batch > 1 way (bench.sim.batched): the same planned episodes, B at a time."""
    from bench.sim import batched

    def ended(row: dict) -> None:
        if on_episode is not None:
            on_episode(row)
        episodes.append(row)
        report(row)

    vector_scenes = vector_scenes or batched.LIBERO_VECTOR
    n = vector_scenes.num_init_states
    for task in spec.tasks:
        planned = [(e, rollout_init_state(e, n), rollout_env_seed(spec.seed, task, e))
                   for e in range(spec.episodes_per_task) if (task, e) not in done]
        episodes += [done[(task, e)] for e in range(spec.episodes_per_task) if (task, e) in done]
        if planned:
            batched.run_task_batched(act, spec, task, planned, descriptions[task], render,
                                     batching, vector_scenes, ended,
                                     lambda step, where: _crash_named(step, where, kept()))
    # Rows in the B = 1 order (task, episode), whatever order the slots finished in.
    order = {t: i for i, t in enumerate(spec.tasks)}
    return sorted(episodes, key=lambda e: (order[e["task"]], e["episode"]))


def _run_on_workers(act: ActFn, spec: RolloutSpec, report: Callable[[dict], None], render,
                    done: dict, on_episode, workers: int, scenes: Scenes, descriptions,
                    episodes: list, kept: Callable[[], str]) -> list[dict]:
    """_run_all's way over worker processes (bench.sim.workers): the same planned episodes."""
    from bench.sim import workers as pool

    if getattr(act, "on_reset", None) is not None:
        raise ValueError("a privileged policy (on_reset) reads its env, which lives in a worker "
                         "process: run it with one worker")

    def ended(row: dict) -> None:
        if on_episode is not None:
            on_episode(row)
        episodes.append(row)
        report(row)

    planned = [(t, e, rollout_env_seed(spec.seed, t, e)) for t in spec.tasks
               for e in range(spec.episodes_per_task) if (t, e) not in done]
    episodes += list(done.values())
    if planned:
        # All W workers even for fewer episodes: the pool is kept for the process's next cell
        # (bench.sim.workers.kept_workers), an idle worker just takes no episode.
        with pool.kept_workers(workers, scenes, spec.suite, render, spec.max_steps,
                               descriptions) as slots:
            pool.run_workers(act, planned, slots, spec, ended,
                             lambda step, where: _crash_named(step, where, kept()))
    order = {t: i for i, t in enumerate(spec.tasks)}
    return sorted(episodes, key=lambda e: (order[e["task"]], e["episode"]))


def _crash_named(step: Callable, where: str, kept: str):
    """`step()`, with an exception turned into RolloutCrashed naming where it happened."""
    try:
        return step()
    except Exception as e:
        raise RolloutCrashed(f"rollout crashed in {where}: {type(e).__name__}: {e} ({kept})") from e


def replay(actions: np.ndarray, suite: str, task: int, init_state: int, env_seed: int,
           render: sim_env.RenderSettings | None = None) -> dict:
    """Execute recorded raw actions (T, 7) open-loop from `init_state`; run_episode's dict."""
    from bench.sim.expert import ReplayPolicy

    render = render or sim_env.RenderSettings()
    env = sim_env.make_env(suite, task, render, max_steps=len(actions))
    try:
        description = sim_env.task_descriptions(suite)[task]
        return run_episode(ReplayPolicy(actions), env, init_state, env_seed, len(actions), 1,
                           description)
    finally:
        env.close()


def summarise(episodes: list[dict], spec: RolloutSpec, render: sim_env.RenderSettings,
              seconds: float, resumed: int = 0) -> dict:
    """The result dict of run_rollouts from its episode rows (`resumed` of them from an earlier,
    interrupted run; `seconds` is this sitting's wall time)."""
    wins = sum(e["success"] for e in episodes)
    per_task = {}
    for task in spec.tasks:
        rows = [e for e in episodes if e["task"] == task]
        k = sum(e["success"] for e in rows)
        per_task[str(task)] = {"successes": k, "episodes": len(rows),
                               "success_rate": k / len(rows) if rows else 0.0,
                               "ci95": list(wilson_interval(k, len(rows)))}
    return {
        "episodes": episodes,
        "success_rate": wins / len(episodes) if episodes else 0.0,
        "per_task": per_task,
        "ci95": list(wilson_interval(wins, len(episodes))),
        "settings": {
            "spec": asdict(spec),
            "libero_suite": sim_env.LIBERO_SUITES[spec.suite],
            "render": render.as_dict(),
            "mujoco_gl": __import__("os").environ.get("MUJOCO_GL"),
            "control_hz": sim_env.CONTROL_HZ,
            "settle_steps": sim_env.SETTLE_STEPS,
            "hard_reset": False,
            "init_states": "official LIBERO init states, episode e -> n-1-e",
            "image_orientation": "LeRobot LIBERO env processor (rotated 180 degrees)",
            "seconds": round(seconds, 1),
            "resumed_episodes": resumed,
        },
    }
