"""One MuJoCo forward pass a physics substep where robosuite runs two on the same state.

robosuite's `env.step` runs, for each physics substep: `sim.forward()`, then `_pre_action` (the
robot's controller calls `update()`, whose `sim.forward()` runs again on the very same state:
nothing has written to it in between but the actuator controls), then `sim.step()`. `mj_forward`
is a function of the state and the controls and writes nothing that its next call reads (the
solver's warm start is written by `mj_step`'s integration), and what the controller reads from it
(positions, velocities, Jacobians, the mass matrix) does not depend on the controls. So the
second call recomputes the bits the first left in `sim.data`: `SkipRepeatForward` skips a forward
that comes, inside `env.step`, right after another with no `sim.step` between them. Everything
else (resets, init states, settling, renders outside a step) forwards as before.
tests/test_sim_frames.py compares the rows and observations with the plain env's, bit for bit.
"""

from __future__ import annotations


class SkipRepeatForward:
    """Installed on one LeRobot LiberoEnv (`env._env.env`: robosuite's env, and its `sim`)."""

    def __init__(self, env) -> None:
        inner = env._env.env
        sim = inner.sim
        self.skipped = 0  # forwards skipped so far (the test reads it: the gate is live)
        self._in_step = False
        self._fresh = False  # inside a step: the last sim call was a forward
        forward, step, env_step = sim.forward, sim.step, inner.step

        def gated_forward():
            if self._in_step and self._fresh:
                self.skipped += 1
                return
            forward()
            self._fresh = self._in_step

        def gated_step(*args, **kwargs):
            self._fresh = False
            return step(*args, **kwargs)

        def gated_env_step(action):
            self._in_step, self._fresh = True, False
            try:
                return env_step(action)
            finally:
                self._in_step = self._fresh = False

        # instance attributes: the controllers hold this sim, LIBERO's wrapper calls this step
        sim.forward, sim.step, inner.step = gated_forward, gated_step, gated_env_step
