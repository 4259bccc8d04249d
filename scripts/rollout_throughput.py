"""Episodes per minute of closed-loop rollouts at a given batch or worker count (docs/PERFORMANCE.md).

Rolls a tiny release (or a zero-action policy: --release zero) out on the sim suite's tasks and
prints one JSON line: batch, env mode, episodes, wall seconds, episodes per minute, load.

    python scripts/rollout_throughput.py RELEASE_DIR --tasks 0,1 --episodes 3 --max-steps 100 \
        --batch 3 --envs async
    python scripts/rollout_throughput.py RELEASE_DIR --tasks 0,1 --episodes 2 --max-steps 280 \
        --workers 2
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

from bench.progress import QUIET


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("release")
    p.add_argument("--tasks", default="0,1")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--envs", default="sync")
    p.add_argument("--n-action-steps", type=int, default=10)
    p.add_argument("--workers", type=int, default=1)
    a = p.parse_args()
    from bench.sim.env import RenderSettings
    from bench.sim.batching import Batching
    from bench.sim.rollout import RolloutSpec, run_rollouts

    if a.release == "zero":
        act = lambda raw: torch.zeros(len(raw["task"]), 10, 7)  # noqa: E731
    else:
        from backbones import adapter_module
        from bench.cell.rollouts import make_act

        name = json.load(open(f"{a.release}/graftbench_release.json"))["backbone"]
        act = make_act(adapter_module(name).load_policy(a.release), noise_seed=0)
    spec = RolloutSpec("spatial", tuple(int(t) for t in a.tasks.split(",")), a.episodes, 0,
                       a.max_steps, a.n_action_steps)
    load_before = os.getloadavg()
    start = time.perf_counter()
    out = run_rollouts(act, spec, progress=QUIET, render=RenderSettings(),
                       batching=Batching(a.batch, a.envs, workers=a.workers))
    wall = time.perf_counter() - start
    n = len(out["episodes"])
    print(json.dumps({"batch": a.batch, "envs": out["settings"]["env_mode"], "episodes": n,
                      "steps": sum(e["steps"] for e in out["episodes"]),
                      "successes": sum(e["success"] for e in out["episodes"]),
                      "wall_s": round(wall, 1), "episodes_per_min": round(60 * n / wall, 2),
                      "load_before": [round(x, 2) for x in load_before],
                      "load_after": [round(x, 2) for x in os.getloadavg()],
                      "rows": [(e["task"], e["episode"], e["success"], e["steps"])
                               for e in out["episodes"]]}), flush=True)


if __name__ == "__main__":
    main()
