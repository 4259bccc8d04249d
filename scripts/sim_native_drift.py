"""Where does the native policy leave its demonstration? (a diagnostic, not a test)

From a TRAINING demonstration's own init state and env seed, roll the release out and print,
at every re-plan, the eef position error against the demo at the same step and the policy's
chunk against the demo's actions there.

    python scripts/sim_native_drift.py RELEASE_DIR --task 0 --init 0 --steps 120 --n-action-steps 10

--rollout: a HELD-OUT init state as the grid's rollouts run it (init state 49 - e, the env seed
of rollout episode e, seed 0); the reference is then the clean expert (--speed) run once from
that same reset (no demonstration exists there).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from backbones import adapter_module
from bench.cell.rollouts import make_act
from bench.sim import demos
from bench.sim import env as sim_env
from bench.sim.expert import episode_seed
from bench.progress import STDERR
from bench.suites import load_suite


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("release")
    p.add_argument("--tasks", default="0,1")
    p.add_argument("--demos", type=int, default=10)
    p.add_argument("--speed", type=float, default=1.0, help="the suite's DemoSpec.expert_speed")
    p.add_argument("--task", type=int, default=0)
    p.add_argument("--init", type=int, default=0)
    p.add_argument("--steps", type=int, default=120)
    p.add_argument("--n-action-steps", type=int, default=10)
    p.add_argument("--rollout", action="store_true",
                   help="held-out init state: rollout env seed, clean expert as the reference")
    a = p.parse_args()
    torch.set_num_threads(1)
    tasks = tuple(int(t) for t in a.tasks.split(","))
    spec = demos.demo_spec("spatial", tasks, a.demos, expert_speed=a.speed)
    suite = load_suite("spatial", "sim", sim_spec=spec, progress=STDERR)
    info = demos.suite_info(suite.root)
    seed = episode_seed(0, a.task, a.init)
    if a.rollout:
        from bench.sim.rollout import rollout_env_seed
        seed = rollout_env_seed(0, a.task, 49 - a.init)
        ref_env = sim_env.make_env("spatial", a.task, demos.render_settings(suite.root), max_steps=280)
        ref = demos.run_expert_episode(ref_env, "spatial", a.task, a.init, 0, 280,
                                       sim_env.task_descriptions("spatial")[a.task],
                                       expert_speed=a.speed)
        ref_env.close()
        print(json.dumps({"reference": "clean expert", "success": ref.success, "steps": ref.steps}))
        demo_state, demo_action = ref.state, ref.action
    else:
        ep = [i for i, e in enumerate(info["episodes"]) if e["task"] == a.task and e["init_state"] == a.init][0]
        rows = suite.episode_index == ep
        demo_state, demo_action = suite.state[rows].numpy(), suite.action[rows].numpy()
    backbone = adapter_module("pi05").load_policy(a.release)
    act = make_act(backbone, noise_seed=0)
    env = sim_env.make_env("spatial", a.task, demos.render_settings(suite.root), max_steps=a.steps)
    desc = sim_env.task_descriptions("spatial")[a.task]
    obs = sim_env.reset_to(env, a.init, seed)
    t = 0
    while t < a.steps:
        raw = sim_env.observe([obs], [desc])
        state = raw["observation.state"][0].numpy()
        chunk = act(raw)[0].numpy()
        d = min(t, len(demo_state) - 1)
        n = min(len(chunk), len(demo_action) - d)
        print(json.dumps({
            "t": t, "eef_err_mm": round(float(np.linalg.norm(state[:3] - demo_state[d, :3])) * 1000, 1),
            "grip_qpos": np.round(state[6:8], 4).tolist(), "demo_grip_qpos": np.round(demo_state[d, 6:8], 4).tolist(),
            "chunk_vs_demo_mse": round(float(((chunk[:n] - demo_action[d:d + n]) ** 2).mean()), 4),
            "a0": np.round(chunk[0], 2).tolist(), "demo_a0": np.round(demo_action[d], 2).tolist()}), flush=True)
        for action in chunk[:a.n_action_steps]:
            obs, _, _, _, inf = env.step(action.astype(np.float64))
            t += 1
            if inf.get("is_success"):
                print(json.dumps({"t": t, "success": True}))
                return
    env.close()


if __name__ == "__main__":
    main()
