"""A scripted pick-and-place expert for LIBERO-Spatial and LIBERO-Object, using privileged poses.

The expert reads object positions straight from the MuJoCo state (it is not a vision policy):
open, move above the object, descend to a grasp point, close, lift, carry above the target,
descend, release, back off. Actions are what LiberoEnv takes and the LeRobot LIBERO datasets
store: OSC_POSE deltas in [-1, 1] (position x/y/z, rotation as axis-angle, scaled by the
controller's 0.05 m / 0.5 rad per unit) and the gripper (-1 open, +1 close).

LIBERO-Spatial: the object is a bowl; the grasp point is a point of its rim (wall at 4.7 cm from
the bowl's centre) at +-y, where the Panda fingers close across the wall with LIBERO's start
orientation; the side with more room from taller neighbours.
LIBERO-Object: a grocery item grasped at its collision-box centre, dropped into the basket.
Measured success per task: docs/LIBERO_SIM.md.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from bench.progress import STDERR, ProgressSink, say


def episode_seed(seed: int, task: int, init_state: int) -> int:
    """The env seed of one attempt: a function of (seed, task, init state) only."""
    digest = hashlib.sha256(f"demo:{seed}:{task}:{init_state}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


# The committed expert's measured success per LIBERO task id, (successes, attempts): seed 0,
# init states 0..4, max 280 steps, no rendering (`python -m bench.sim.expert`; the tables of
# docs/LIBERO_SIM.md). A task it never solved cannot give demonstrations: refused at start-up.
MEASURED_SUCCESS = {
    "spatial": {0: (5, 5), 1: (5, 5), 2: (5, 5), 3: (5, 5), 4: (0, 5), 5: (5, 5), 6: (5, 5),
                7: (5, 5), 8: (1, 5), 9: (3, 5)},
    "object": {0: (5, 5), 1: (0, 5), 2: (5, 5), 3: (5, 5), 4: (5, 5), 5: (5, 5), 6: (0, 5),
               7: (5, 5), 8: (5, 5), 9: (5, 5)},
}


def check_solvable(suite: str, tasks) -> None:
    """ValueError naming every task id of `suite` the expert cannot solve (or that LIBERO lacks),
    with its measured success and the ids to choose instead."""
    measured = MEASURED_SUCCESS.get(suite)
    if measured is None:
        raise ValueError(f"suite {suite!r} has no scripted expert; choose one of "
                         f"{sorted(MEASURED_SUCCESS)}")
    unknown = [t for t in tasks if t not in measured]
    unsolved = [t for t in tasks if t in measured and measured[t][0] == 0]
    if not unknown and not unsolved:
        return
    solved = ",".join(str(t) for t, (k, n) in measured.items() if k == n)
    partly = ", ".join(f"{t} ({k}/{n})" for t, (k, n) in measured.items() if 0 < k < n)
    why = [f"task {t} is not a LIBERO-{suite} task id (0..{len(measured) - 1})" for t in unknown]
    why += [f"the scripted expert cannot solve LIBERO-{suite} task {t} (measured "
            f"{measured[t][0]}/{measured[t][1]} from init states 0..4, docs/LIBERO_SIM.md)"
            for t in unsolved]
    raise ValueError(f"{'; '.join(why)}; choose from {solved} (expert 100%)"
                     + (f" or {partly}" if partly else ""))


POS_SCALE = 0.05  # metres per action unit (OSC_POSE output_max)
ROT_SCALE = 0.5  # radians per action unit
OPEN, CLOSE = -1.0, 1.0


@dataclass(frozen=True)
class ExpertParams:
    """Geometry and gains of the scripted expert (metres, steps)."""

    approach_height: float = 0.10  # above the grasp point before descending
    carry_height: float = 0.18  # above the target's origin while carrying
    min_lift: float = 0.06  # at least this far above the grasp point while carrying
    grasp_depth: float = 0.0  # eef height over the grip reference (rim top / object centre)
    bowl_rim_radius: float = 0.047  # akita black bowl: wall boxes at 4.7 cm from the centre
    bowl_rim_top: float = 0.053  # wall top above the bowl body's origin
    release_height: float = 0.07  # eef above the target's origin when opening (bowl on plate)
    object_grip_below_top: float = 0.03  # LIBERO-Object: eef this far under the item's top
    object_drop_margin: float = 0.03  # LIBERO-Object: item bottom above the basket rim on release
    gain: float = 12.0  # action units per metre of position error, clipped to [-1, 1] (x POS_SCALE)
    # Below 1: the translation is capped at `speed` with its direction kept (same gain
    # inside the cap: halving it let the loaded arm sag out of the transit tolerance), so moves
    # are no longer saturated at +-1 per axis (a constant label carries no feedback, and a learned
    # policy undershot it); waypoint timeouts grow by 1/speed. 1: the original per-axis clip.
    speed: float = 1.0
    rot_gain: float = 1.0  # action units per radian of orientation error
    rot_tolerance: float = 0.05  # radians: orientation held this well before grasping
    tolerance: float = 0.012  # metres: a precise waypoint (grasp point) counts as reached
    transit_tolerance: float = 0.03  # metres: a transit waypoint (loaded arm sags a little)
    close_steps: int = 12
    open_steps: int = 10
    waypoint_timeout: int = 50  # steps before a waypoint is abandoned (the episode then fails)


def _rotation_error(current: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Axis-angle (3,) rotating `current` (3x3) onto `goal` (3x3), in the world frame."""
    delta = goal @ current.T
    cos = np.clip((np.trace(delta) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    if angle < 1e-6:
        return np.zeros(3)
    axis = np.array([delta[2, 1] - delta[1, 2], delta[0, 2] - delta[2, 0], delta[1, 0] - delta[0, 1]])
    return axis / (2.0 * np.sin(angle)) * angle


class ScriptedExpert:
    """Waypoint state machine for one LiberoEnv episode; call `reset(env)` after each env reset."""

    def __init__(self, suite: str, params: ExpertParams = ExpertParams()):
        if suite not in ("spatial", "object"):
            raise ValueError(f"no scripted expert for suite {suite!r}; choose 'spatial' or 'object'")
        self.suite = suite
        self.params = params

    # -- privileged state -------------------------------------------------------------------
    def _inner(self, env):
        return env._env.env  # LiberoEnv -> OffScreenRenderEnv -> LIBERO problem env

    def _body_pos(self, env, name: str) -> np.ndarray:
        inner = self._inner(env)
        return np.array(inner.sim.data.body_xpos[inner.obj_body_id[name]])

    def _eef(self, env) -> tuple[np.ndarray, np.ndarray]:
        robot = self._inner(env).robots[0]
        return np.array(robot.controller.ee_pos), np.array(robot.controller.ee_ori_mat)

    # -- plan -------------------------------------------------------------------------------
    def reset(self, env) -> None:
        """Plan waypoints from the current object poses (call after the env was reset)."""
        p = self.params
        picked, target = self._inner(env).obj_of_interest[:2]
        self.picked_name, self.target_name = picked, target
        _, self.goal_ori = self._eef(env)
        obj = self._body_pos(env, picked)
        if self.suite == "spatial":
            side = self._rim_side(env, obj)
            grip = obj + np.array([0.0, side * p.bowl_rim_radius, p.bowl_rim_top])
        else:
            # Grocery item: its collision box centre in xy, a few cm under its top (not below
            # 2.8 cm over its bottom: the fingertips reach ~2 cm under the eef).
            lo, hi = self._aabb(env, picked)
            grip = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2,
                             max(hi[2] - p.object_grip_below_top, lo[2] + 0.028)])
            basket_lo, basket_hi = self._aabb(env, target)
            # Release with the item's bottom a little above the basket's rim, over its centre.
            self.object_place = np.array([(basket_lo[0] + basket_hi[0]) / 2,
                                          (basket_lo[1] + basket_hi[1]) / 2,
                                          basket_hi[2] + (grip[2] - lo[2]) + p.object_drop_margin])
        self.grip_offset = grip - obj
        self.grip_offset[2] += p.grasp_depth
        self.phase = 0
        self.phase_steps = 0
        self.done = False
        self.frozen_grip = None

    def _rim_side(self, env, obj: np.ndarray) -> float:
        """+1 or -1: the rim point (along world y) with more room for the fingers.

        Room = horizontal distance to the nearest taller neighbour's collision footprint; a near
        tie goes to the side nearer y = 0. (Turning the gripper 90 degrees to grasp at +-x was
        tried: it fixed LIBERO-Spatial task 8 but broke tasks 0 and 2, so it is not used.)
        """
        p = self.params
        finger_bottom = obj[2] + p.bowl_rim_top + p.grasp_depth - 0.035  # fingertips below eef
        obstacles = [fp for fp in self._footprints(env) if fp[2] > finger_bottom]

        def room(side: float) -> float:
            point = obj[:2] + np.array([0.0, side * p.bowl_rim_radius])
            return min((np.linalg.norm(centre - point) - radius for centre, radius, _ in obstacles),
                       default=1.0)

        plus, minus = room(1.0), room(-1.0)
        if abs(plus - minus) < 0.01:
            return -1.0 if obj[1] > 0 else 1.0
        return 1.0 if plus > minus else -1.0

    def _footprints(self, env) -> list[tuple[np.ndarray, float, float]]:
        """(xy centre, horizontal radius, top z) of every other object's collision geoms."""
        inner = self._inner(env)
        model, data = inner.sim.model, inner.sim.data
        picked = inner.obj_body_id[self.picked_name]
        out = []
        for name, body in inner.obj_body_id.items():
            if body == picked:
                continue
            geoms = [g for g in range(model.ngeom) if model.geom_contype[g] != 0
                     and self._root_of(model, model.geom_bodyid[g]) == body]
            if not geoms:
                continue
            xy = data.geom_xpos[geoms, :2]
            centre = xy.mean(axis=0)
            half = [self._half_extents(model, data, g) for g in geoms]
            radius = max(np.linalg.norm(xy[i] - centre) + np.linalg.norm(half[i][:2])
                         for i in range(len(geoms)))
            top = max(data.geom_xpos[g, 2] + half[i][2] for i, g in enumerate(geoms))
            out.append((centre, float(radius), float(top)))
        return out

    def _aabb(self, env, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned box (lo (3,), hi (3,)) around an object's collision geoms."""
        inner = self._inner(env)
        model, data = inner.sim.model, inner.sim.data
        body = inner.obj_body_id[name]
        geoms = [g for g in range(model.ngeom) if model.geom_contype[g] != 0
                 and self._root_of(model, model.geom_bodyid[g]) == body]
        half = np.array([self._half_extents(model, data, g) for g in geoms])
        return (data.geom_xpos[geoms] - half).min(axis=0), (data.geom_xpos[geoms] + half).max(axis=0)

    @staticmethod
    def _half_extents(model, data, geom: int) -> np.ndarray:
        """World-axis half extents (3,) of a geom: exact for boxes, bounding sphere otherwise."""
        if model.geom_type[geom] == 6:  # mjGEOM_BOX
            rotation = data.geom_xmat[geom].reshape(3, 3)
            return np.abs(rotation) @ model.geom_size[geom]
        return np.full(3, model.geom_rbound[geom])

    @staticmethod
    def _root_of(model, body: int) -> int:
        """The child of the world body that `body` hangs from (an object's own body id)."""
        while model.body_parentid[body] != 0:
            body = model.body_parentid[body]
        return body

    def _waypoints(self, env) -> list[tuple[np.ndarray, float, str]]:
        """(eef target, gripper command, kind) for each phase, from the current poses."""
        p = self.params
        if self.phase == 0 or self.frozen_grip is None:
            # The grasp point follows the object until the descent begins, then stays fixed.
            self.frozen_grip = self._body_pos(env, self.picked_name) + self.grip_offset
        grip = self.frozen_grip
        target = self._body_pos(env, self.target_name)
        up = np.array([0.0, 0.0, 1.0])
        if self.suite == "spatial":
            place = target + np.array([self.grip_offset[0], self.grip_offset[1], 0.0]) \
                + up * p.release_height
        else:
            place = self.object_place
        carry_z = max(target[2] + p.carry_height, grip[2] + p.min_lift, place[2] + 0.05)
        carry = np.array([place[0], place[1], carry_z])
        lift = np.array([grip[0], grip[1], carry_z])
        return [
            (grip + up * p.approach_height, OPEN, "transit"),
            (grip, OPEN, "move"),
            (grip, CLOSE, "grip"),
            (lift, CLOSE, "transit"),
            (carry, CLOSE, "transit"),
            (place, CLOSE, "transit"),
            (place, OPEN, "release"),
            (place + up * p.approach_height, OPEN, "transit"),
        ]

    def __call__(self, env) -> np.ndarray:
        """The next action (7,) float32 for `env` in its current state."""
        p = self.params
        pos, ori = self._eef(env)
        waypoints = self._waypoints(env)
        if self.phase >= len(waypoints):
            self.done = True
            target, gripper, kind = waypoints[-1]
        else:
            target, gripper, kind = waypoints[self.phase]
        action = np.zeros(7, dtype=np.float32)
        action[:3] = self._translation(target - pos)
        rotation_error = _rotation_error(ori, self.goal_ori)
        action[3:6] = np.clip(p.rot_gain * rotation_error / ROT_SCALE, -1.0, 1.0)
        action[6] = gripper
        self._advance(kind, np.linalg.norm(target - pos), float(np.linalg.norm(rotation_error)))
        return action

    def _translation(self, error: np.ndarray) -> np.ndarray:
        """Translation action (3,) for a position error (metres): see ExpertParams.speed."""
        p = self.params
        if p.speed >= 1.0:
            return np.clip(p.gain * error, -1.0, 1.0)
        action = p.gain * error
        largest = np.abs(action).max()
        return action * (p.speed / largest) if largest > p.speed else action

    def _advance(self, kind: str, error: float, rotation_error: float) -> None:
        p = self.params
        self.phase_steps += 1
        if kind == "grip":
            finished = self.phase_steps >= p.close_steps
        elif kind == "release":
            finished = self.phase_steps >= p.open_steps
        else:
            tolerance = p.transit_tolerance if kind == "transit" else p.tolerance
            aligned = self.phase >= 2 or rotation_error < p.rot_tolerance  # upright before grasping
            timeout = p.waypoint_timeout / min(p.speed, 1.0)  # a slower expert needs longer
            finished = (error < tolerance and aligned) or self.phase_steps >= timeout
        if finished and not self.done:
            self.phase += 1
            self.phase_steps = 0


class ExpertPolicy:
    """The scripted expert as a rollout `act`: (raw obs) -> (B, 1, 7) raw actions.

    Privileged: it ignores the observation and reads the simulator, so run_rollouts hands it the
    envs after each reset (`on_reset`). For known-answer tests of the rollout path only.
    """

    def __init__(self, suite: str, params: ExpertParams = ExpertParams()):
        self.suite, self.params = suite, params
        self.envs: list = []
        self.experts: list[ScriptedExpert] = []

    def on_reset(self, envs: list) -> None:
        self.envs = list(envs)
        self.experts = [ScriptedExpert(self.suite, self.params) for _ in self.envs]
        for expert, env in zip(self.experts, self.envs):
            expert.reset(env)

    def __call__(self, raw: dict):
        import torch

        actions = [expert(env) for expert, env in zip(self.experts, self.envs)]
        return torch.from_numpy(np.stack(actions)).float().unsqueeze(1)


class ReplayPolicy:
    """Replays a recorded action sequence (T, 7) one step per call: (B=1, 1, 7)."""

    def __init__(self, actions: np.ndarray):
        self.actions = np.asarray(actions, dtype=np.float32)
        self.t = 0

    def on_reset(self, envs: list) -> None:
        self.t = 0

    def __call__(self, raw: dict):
        import torch

        index = min(self.t, len(self.actions) - 1)
        self.t += 1
        return torch.from_numpy(self.actions[index]).view(1, 1, 7)


def measure(suite: str, tasks: list[int], init_states: list[int], seed: int = 0,
            max_steps: int = 280, *, progress: ProgressSink, speed: float = 1.0) -> dict:
    """Expert success per task without rendering (cameras off while stepping): a measurement.

    Returns {task: {"successes", "attempts", "steps": [...], "seconds": [...]}}.
    """
    import time

    from bench.sim import env as sim_env

    out = {}
    for task in tasks:
        env = sim_env.make_env(suite, task)
        rows = {"successes": 0, "attempts": 0, "steps": [], "seconds": [], "success": []}
        for init_state in init_states:
            start = time.perf_counter()
            sim_env.reset_to(env, init_state, episode_seed(seed, task, init_state))
            sim_env.set_cameras(env, False)
            expert = ScriptedExpert(suite, ExpertParams(speed=speed))
            expert.reset(env)
            success, steps = False, 0
            while steps < max_steps and not success:
                env._env.step(expert(env).astype(np.float64))
                steps += 1
                success = bool(env._env.check_success())
            sim_env.set_cameras(env, True)
            rows["attempts"] += 1
            rows["successes"] += int(success)
            rows["success"].append(success)
            rows["steps"].append(steps)
            rows["seconds"].append(round(time.perf_counter() - start, 2))
            say(progress, f"expert: {suite} task {task} init {init_state}: "
                          f"{'success' if success else 'failure'} in {steps} steps "
                          f"({rows['seconds'][-1]:.1f} s)")
        env.close()
        out[str(task)] = rows
    return out


if __name__ == "__main__":
    import argparse
    import json

    parser = argparse.ArgumentParser(description="measure the scripted expert's success")
    parser.add_argument("--suite", default="spatial")
    parser.add_argument("--tasks", default="0,1,2,3,4,5,6,7,8,9")
    parser.add_argument("--init-states", type=int, default=10, help="init states 0..N-1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="write the result JSON here")
    parser.add_argument("--speed", type=float, default=1.0, help="ExpertParams.speed")
    args = parser.parse_args()
    result = measure(args.suite, [int(t) for t in args.tasks.split(",")],
                     list(range(args.init_states)), args.seed, progress=STDERR,
                     speed=args.speed)
    text = json.dumps(result, indent=1)
    if args.out:
        open(args.out, "w").write(text)
    summary = {t: f"{r['successes']}/{r['attempts']}" for t, r in result.items()}
    print(json.dumps(summary))
