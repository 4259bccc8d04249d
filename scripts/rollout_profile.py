"""Where a closed-loop step's time goes: physics, camera renders, observation processing, the
policy call, resets (docs/PERFORMANCE.md, "Closed-loop rollouts").

Runs the rollout loop of bench.sim.rollout by hand on an env that renders every step (the loop
before frames were gated), timing each part; camera renders are timed inside robosuite's camera
sensors, so "physics" is a step's time without them. Prints one JSON line.

    python scripts/rollout_profile.py RELEASE_DIR --tasks 0,1 --episodes 2 [--gated]

--gated: the same loop as rollouts run it: frames rendered only where read (bench.sim.frames)
and one MuJoCo forward a physics substep (bench.sim.physics).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import defaultdict

import torch

from bench.sim import env as sim_env
from bench.sim.episode import next_actions, rollout_init_state
from bench.sim.rollout import rollout_env_seed


def tick() -> tuple[float, float]:
    """(wall, process CPU) seconds: on shared cores a part's wall time includes waiting for a
    core, its CPU time (all threads, llvmpipe's render threads too) does not."""
    return time.perf_counter(), time.process_time()


def since(start: tuple[float, float]) -> tuple[float, float]:
    now = tick()
    return now[0] - start[0], now[1] - start[1]


def timed_cameras(env, clock: dict, phase: list) -> None:
    """Wrap the camera sensors so each frame's render adds to clock["render_<phase[0]>"]."""
    for name in sim_env.CAMERA_MAPPING:
        observable = env._env.env._observables[name]
        render = observable._sensor

        def sensor(cache, render=render):
            start = tick()
            frame = render(cache)
            if cache:
                clock[f"render_{phase[0]}"].append(since(start))
            return frame

        sensor.__modality__ = render.__modality__
        observable.set_sensor(sensor)


def episode(act, env, task: int, e: int, description: str, clock: dict, phase: list,
            n: int = 10) -> dict:
    """run_episode's loop with a clock on each part; returns its row."""
    start, phase[0] = tick(), "reset"
    obs = sim_env.reset_to(env, rollout_init_state(e, 50), rollout_env_seed(0, task, e))
    clock["reset"].append(since(start))
    phase[0] = "step"
    steps, success = 0, False
    while steps < 280 and not success:
        t0 = tick()
        raw = sim_env.observe([obs], [description])
        clock["observe"].append(since(t0))
        t1 = tick()
        actions = next_actions(act, raw, n)
        clock["policy"].append(since(t1))
        sim_env.read_after(env, len(actions) if len(actions) < 280 - steps else None)
        for action in actions[:280 - steps]:
            t0 = tick()
            obs, _, _, _, info = env.step(action)
            clock["step"].append(since(t0))
            steps += 1
            success = bool(info.get("is_success", False))
            if success:
                break
    return {"task": task, "episode": e, "success": success, "steps": steps}


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("release")
    p.add_argument("--tasks", default="0,1")
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--gated", action="store_true")
    a = p.parse_args()
    from backbones import adapter_module
    from bench.cell.rollouts import make_act

    torch.set_num_threads(1)
    name = json.load(open(f"{a.release}/graftbench_release.json"))["backbone"]
    act = make_act(adapter_module(name).load_policy(a.release), noise_seed=0)
    clock, rows, phase = defaultdict(list), [], ["build"]
    descriptions = sim_env.task_descriptions("spatial")
    for task in (int(t) for t in a.tasks.split(",")):
        start = tick()
        env = sim_env.make_env("spatial", task, sim_env.RenderSettings(), max_steps=280)
        clock["env_build"].append(since(start))
        timed_cameras(env, clock, phase)
        if a.gated:  # gate the timed sensors: only real renders are timed
            sim_env.install_gates(env)
        rows += [episode(act, env, task, e, descriptions[task], clock, phase)
                 for e in range(a.episodes)]
        env.close()
    print(json.dumps({
        "gated": a.gated, "rows": rows, "load": os.getloadavg(),
        "wall_ms": {k: round(1000 * sum(w for w, _ in v) / len(v), 1) for k, v in clock.items()},
        "cpu_ms": {k: round(1000 * sum(c for _, c in v) / len(v), 1) for k, v in clock.items()},
        "count": {k: len(v) for k, v in clock.items()},
        "cpu_total_s": {k: round(sum(c for _, c in v), 1) for k, v in clock.items()}}))


if __name__ == "__main__":
    main()
