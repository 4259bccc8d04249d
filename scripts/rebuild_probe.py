"""Which part of a tiny release rebuilds bit for bit here (studies/sim/REBUILD.md): prints hashes
to compare between two runs, two settings or two machines.

    python scripts/rebuild_probe.py render          # 1 LIBERO task x 1 demo, the closed-loop spec
    python scripts/rebuild_probe.py frames          # its first 5 agentview frames only (seconds)
    python scripts/rebuild_probe.py train pi05 200  # a 200-step tiny release (tiny profile)

Both write into GRAFTBENCH_CACHE: give each run an empty one (e.g. /tmp/probeA).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import sys
import time

import numpy as np


def render() -> None:
    """The closed-loop recipe's demo spec (noise 0.1, speed 0.5) cut to task 0, one demo."""
    from bench.progress import STDERR
    from bench.sim.demos import demo_spec, generate
    from bench.sim.env import configure
    from bench.suites import load_suite

    spec = demo_spec("spatial", (0,), 1, 0.1, 0.5)
    start = time.time()
    root = generate(spec, None, STDERR)
    configure()
    print(f"rendered {root} in {time.time() - start:.0f} s; MUJOCO_GL={os.environ['MUJOCO_GL']}")
    for path in sorted((root.parent / f"{root.name}.work" / "episodes").glob("*.npz")):
        with np.load(path) as data:
            for key in sorted(data.files):
                digest = hashlib.sha256(np.ascontiguousarray(data[key]).tobytes()).hexdigest()
                print(f"{path.name} {key} {data[key].shape} sha256:{digest[:16]}")
    suite = load_suite("spatial", "sim", sim_spec=spec, progress=STDERR)
    print("suite fingerprint", suite.fingerprint)


def frames() -> None:
    """The first 5 agentview frames of `render`'s first attempt (task 0, init state 0), and the
    GL renderer that drew them: a slow rasteriser's check in seconds instead of minutes."""
    from bench.sim import env as sim_env
    from bench.sim.expert import ExpertParams, ScriptedExpert, episode_seed
    from ondisk.libero_format import IMAGE_KEYS

    env = sim_env.make_env("spatial", 0, max_steps=280)
    obs = sim_env.reset_to(env, 0, episode_seed(0, 0, 0))
    expert = ScriptedExpert("spatial", ExpertParams(speed=0.5))
    expert.reset(env)
    images = []
    for _ in range(5):
        images.append(sim_env.to_uint8_hwc(sim_env.observe([obs], ["-"])[IMAGE_KEYS[0]][0]))
        obs, *_ = env.step(expert(env).astype(np.float64))
    import OpenGL.GL as GL

    digest = hashlib.sha256(np.stack(images).tobytes()).hexdigest()[:16]
    print(f"renderer {GL.glGetString(GL.GL_RENDERER).decode()}; 5 frames sha256:{digest}")


def train(name: str, steps: int) -> None:
    """The tiny profile's native training of `name`, cut to `steps`: its weights' sha256."""
    import torch

    from bench.grid.protocol import TINY
    from bench.progress import STDERR
    from bench.results.store import ResultStore
    from bench.resources.workspace import Workspace

    profile = dataclasses.replace(TINY, protocol=TINY.protocol.replace(native_steps=steps))
    cache = os.environ["GRAFTBENCH_CACHE"]
    ws = Workspace(profile, ResultStore(f"{cache}/results"), progress=STDERR)
    start = time.time()
    revision = ws.checkpoint(name)["revision"]
    print(f"{name} {steps} native steps: revision {revision}; torch {torch.__version__}, "
          f"{torch.get_num_threads()} thread(s), {torch.backends.cpu.get_cpu_capability()} "
          f"kernels, {time.time() - start:.0f} s")


if __name__ == "__main__":
    if "GRAFTBENCH_CACHE" not in os.environ or sys.argv[1:2] not in (["render"], ["frames"],
                                                                     ["train"]):
        sys.exit(__doc__)
    if sys.argv[1] == "train":
        train(sys.argv[2], int(sys.argv[3]))
    else:
        render() if sys.argv[1] == "render" else frames()
