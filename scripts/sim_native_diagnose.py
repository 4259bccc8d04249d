"""Why does the tiny native policy never succeed? A diagnostic outside the test suite.

1. Open loop: the trained release's action chunks on the demonstrations' own frames against the
   demonstrations' actions (raw units, per dimension; gripper sign agreement).
2. Closed loop from the demonstrations' OWN init states (training episodes): failing even there
   means closed-loop drift or a convention mismatch, not generalisation to new init states.

    python scripts/sim_native_diagnose.py RELEASE_DIR --tasks 0,1 --demos 10 --episodes 2 \
        --n-action-steps 10
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from backbones import adapter_module
from bench.cell.rollouts import make_act
from bench.sim import demos
from bench.sim import env as sim_env
from bench.sim.rollout import run_episode
from bench.progress import STDERR
from bench.suites import load_suite
from bench.suites.windows import raw_batch


def open_loop(backbone, act, suite, episodes: list[int], stride: int = 5) -> dict:
    """Raw-unit error of the policy's chunks on demo frames, per action dimension."""
    frames = torch.nonzero(torch.isin(suite.episode_index, torch.tensor(episodes))).flatten()
    frames = frames[suite.frame_index[frames] % stride == 0]
    errs, signs, first = [], [], []
    for start in range(0, len(frames), 16):
        batch = raw_batch(suite, frames[start:start + 16], backbone.info.chunk_size)
        pred = act({k: v for k, v in batch.items() if k not in ("action", "action_is_pad")})
        target = batch["action"]
        keep = ~batch["action_is_pad"]
        errs.append(((pred - target) ** 2)[keep])
        signs.append((torch.sign(pred[..., 6]) == torch.sign(target[..., 6]))[keep].float())
        first.append(((pred[:, 0] - target[:, 0]) ** 2))
    err = torch.cat(errs)
    return {"windows": len(frames), "mse_per_dim": err.mean(0).round(decimals=5).tolist(),
            "mse": round(float(err.mean()), 5),
            "first_step_mse": round(float(torch.cat(first).mean()), 5),
            "gripper_sign_agreement": round(float(torch.cat(signs).mean()), 3),
            "action_std_per_dim": suite.action.std(0).round(decimals=4).tolist()}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("release")
    parser.add_argument("--tasks", default="0,1")
    parser.add_argument("--demos", type=int, default=10)
    parser.add_argument("--speed", type=float, default=1.0, help="the suite's DemoSpec.expert_speed")
    parser.add_argument("--episodes", type=int, default=2, help="closed-loop episodes per task")
    parser.add_argument("--n-action-steps", type=int, default=10)
    parser.add_argument("--max-steps", type=int, default=280)
    parser.add_argument("--init-states", default="demo", help="'demo' or comma list")
    args = parser.parse_args()
    torch.set_num_threads(1)
    tasks = tuple(int(t) for t in args.tasks.split(","))
    spec = demos.demo_spec("spatial", tasks, args.demos, expert_speed=args.speed)
    suite = load_suite("spatial", "sim", sim_spec=spec, progress=STDERR)
    info = demos.suite_info(suite.root)
    backbone = adapter_module(json.load(open(f"{args.release}/graftbench_release.json"))
                              ["backbone"]).load_policy(args.release)
    act = make_act(backbone, noise_seed=0)
    ids = demos.libero_task_ids(suite.root)
    for task_index, task in enumerate(ids):
        eps = sorted({int(e) for e in suite.episode_index[suite.task_index == task_index].tolist()})
        print(json.dumps({"task": task, "open_loop": open_loop(backbone, act, suite, eps)}),
              flush=True)
    render = demos.render_settings(suite.root)
    descriptions = sim_env.task_descriptions("spatial")
    for task in tasks:
        if args.init_states == "demo":
            inits = [e["init_state"] for e in info["episodes"] if e["task"] == task]
        else:
            inits = [int(i) for i in args.init_states.split(",")]
        env = sim_env.make_env("spatial", task, render, max_steps=args.max_steps)
        try:
            for init in inits[:args.episodes]:
                from bench.sim.expert import episode_seed
                t0 = time.time()
                row = run_episode(act, env, init, episode_seed(0, task, init), args.max_steps,
                                  args.n_action_steps, descriptions[task])
                print(json.dumps({"task": task, **row, "wall": round(time.time() - t0, 1)}),
                      flush=True)
        finally:
            env.close()


if __name__ == "__main__":
    main()
