"""Camera frames rendered only at the control steps whose observation is read.

robosuite samples each camera observable once per control step (at the step's first physics
substep) and renders it then, whether or not anyone reads the frame; the rollout loop reads one
observation per action chunk (every `n_action_steps` steps) and one after each reset's settle
steps. `FrameGate` wraps the camera sensors so that a sample renders only at the control step
named by `read_after`; any other sample returns a black placeholder nobody reads. Physics,
robot state and every observable's sampling clock are untouched, so the frames that are read
are the very frames of an env that renders every step (tests/test_sim_frames.py).
"""

from __future__ import annotations

import numpy as np


class FrameGateMissed(RuntimeError):
    """A frame the loop reads was not rendered at its step: never silently a placeholder."""


class FrameGate:
    """Lazy camera sensors on one LeRobot LiberoEnv (`env._env.env`: robosuite's env)."""

    def __init__(self, env, cameras) -> None:
        self._inner = env._env.env
        self.read_at: int | None = None  # robosuite timestep whose frames are read
        self.rendered_at: int | None = None  # timestep of the last real render
        for name in cameras:
            self._wrap(self._inner._observables[name])

    def _wrap(self, observable) -> None:
        render = observable._sensor
        blank: list[np.ndarray] = []
        probing = [True]  # set_sensor probes the sensor once for its shape: a real frame

        def gated(obs_cache):
            if probing[0]:
                blank.append(np.zeros_like(render(obs_cache)))
                return blank[0]
            if self._inner.timestep != self.read_at:
                return blank[0]
            self.rendered_at = self._inner.timestep
            return render(obs_cache)

        gated.__modality__ = render.__modality__
        observable.set_sensor(gated)
        probing[0] = False

    def read_after(self, steps: int | None) -> None:
        """The observation after `steps` more control steps is read (None: none is): render
        only there. Checks first that the frame read last (at the step now reached) was real."""
        self.check()
        self.read_at = None if steps is None else self._inner.timestep + steps

    def read_after_reset(self, settle_steps: int) -> None:
        """A soft reset zeroes robosuite's timestep, then settles `settle_steps` steps."""
        self.read_at = settle_steps

    def check(self) -> None:
        now = self._inner.timestep
        if self.read_at == now and self.rendered_at != now:
            raise FrameGateMissed(f"the frame of control step {now} was read but not rendered "
                                  f"(last render at step {self.rendered_at})")
