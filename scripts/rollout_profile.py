"""Where a closed-loop step's time goes: physics, camera renders, observation processing, the
policy call, resets (docs/PERFORMANCE.md, "Closed-loop rollouts").

Runs the rollout loop of bench.sim.rollout by hand on an env that renders every step (the loop
before frames were gated), timing each part; camera renders are timed inside robosuite's camera
sensors, so "physics" is a step's time without them. Prints one JSON line.

    python scripts/rollout_profile.py RELEASE_DIR --tasks 0,1 --episodes 2
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import defaultdict

import torch

from bench.sim import env as sim_env
from bench.sim.rollout import next_actions, rollout_env_seed, rollout_init_state


def timed_cameras(env, clock: dict, phase: list) -> None:
    """Wrap the camera sensors so each frame's render adds to clock["render_<phase[0]>"]."""
    for name in sim_env.CAMERA_MAPPING:
        observable = env._env.env._observables[name]
        render = observable._sensor

        def sensor(cache, render=render):
            start = time.perf_counter()
            frame = render(cache)
            if cache:
                clock[f"render_{phase[0]}"].append(time.perf_counter() - start)
            return frame

        sensor.__modality__ = render.__modality__
        observable.set_sensor(sensor)


def episode(act, env, task: int, e: int, description: str, clock: dict, phase: list,
            n: int = 10) -> dict:
    """run_episode's loop with a clock on each part; returns its row."""
    tick = time.perf_counter
    start, phase[0] = tick(), "reset"
    obs = sim_env.reset_to(env, rollout_init_state(e, 50), rollout_env_seed(0, task, e))
    clock["reset"].append(tick() - start)
    phase[0] = "step"
    steps, success = 0, False
    while steps < 280 and not success:
        t0 = tick()
        raw = sim_env.observe([obs], [description])
        t1 = tick()
        actions = next_actions(act, raw, n)
        clock["observe"].append(t1 - t0)
        clock["policy"].append(tick() - t1)
        for action in actions[:280 - steps]:
            t0 = tick()
            obs, _, _, _, info = env.step(action)
            clock["step"].append(tick() - t0)
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
    a = p.parse_args()
    from backbones import adapter_module
    from bench.cell.rollouts import make_act

    torch.set_num_threads(1)
    name = json.load(open(f"{a.release}/graftbench_release.json"))["backbone"]
    act = make_act(adapter_module(name).load_policy(a.release), noise_seed=0)
    clock, rows, phase = defaultdict(list), [], ["build"]
    descriptions = sim_env.task_descriptions("spatial")
    for task in (int(t) for t in a.tasks.split(",")):
        start = time.perf_counter()
        env = sim_env.make_env("spatial", task, sim_env.RenderSettings(), max_steps=280)
        clock["env_build"].append(time.perf_counter() - start)
        timed_cameras(env, clock, phase)
        rows += [episode(act, env, task, e, descriptions[task], clock, phase)
                 for e in range(a.episodes)]
        env.close()
    print(json.dumps({
        "rows": rows, "load": os.getloadavg(),
        "ms": {k: round(1000 * sum(v) / len(v), 1) for k, v in clock.items()},
        "count": {k: len(v) for k, v in clock.items()},
        "total_s": {k: round(sum(v), 1) for k, v in clock.items()}}))


if __name__ == "__main__":
    main()
