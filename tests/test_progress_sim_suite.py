"""A first-use sim suite renders its demonstrations for ~10 minutes inside `pytest
bench`; its per-attempt lines must reach the terminal, not pytest's captured stderr (they did
not: `_sim_suite_path` called `demos.generate` without the session's sink).

No simulator here (the libero extra is optional): the run takes the real path, session ->
workspace -> load_suite -> _sim_suite_path -> demos.generate -> run_attempts, with only the
simulator's own calls stood in (an env that is never stepped, an expert episode of three
blank frames) and LeRobot's dataset writer stopped, so the run ends at the suite (its one cell
fails).
"""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np

from bench.sim import demos
from bench.sim import env as sim_env
from bench.suites.base import SuiteUnavailable

ONE_CELL = ["--profile", "sim", "--backbones", "pi05", "--suites", "spatial", "--encoders",
            "blind", "--seeds", "0", "--controls", "none", "--steps", "2"]


class _Clock:
    """bench.progress's clock, moved by hand: an attempt that renders for 40 s."""

    now = 1000.0

    def __call__(self) -> float:
        return self.now


def _episode(env, suite, task, init_state, seed, max_steps, description, *rest,
             on_step=None) -> demos.Episode:
    """The expert's attempt, stood in: task 1 fails its first init state (a line says so); the
    first attempt takes 40 s of the progress clock (a line inside it says how far it is)."""
    if task == 0 and init_state == 0:
        for step in range(max_steps):
            _Clock.now += 40.0 / max_steps
            on_step(step)
    size = demos.DEFAULT_SPECS[suite].image_size
    frames = np.zeros((3, size, size, 3), np.uint8)
    return demos.Episode(task, init_state, not (task == 1 and init_state == 0), frames, frames,
                         np.zeros((3, 8), np.float32), np.zeros((3, 7), np.float32), seconds=0.1)


def _stop(*args, **kwargs):
    raise SuiteUnavailable("stand-in: the dataset is not written without the simulator")


def test_first_use_sim_suite_reports_each_attempt_on_the_terminal(tmp_path, monkeypatch):
    from tests.bench_inprocess import run_bench

    monkeypatch.setattr(sim_env, "libero_available", lambda: True)
    monkeypatch.setattr(sim_env, "task_descriptions", lambda suite: [f"t{i}" for i in range(10)])
    monkeypatch.setattr(sim_env, "make_env", lambda *a, **k: SimpleNamespace(close=lambda: None))
    monkeypatch.setattr(demos, "run_expert_episode", _episode)
    monkeypatch.setattr("bench.progress.clock", _Clock())
    monkeypatch.setattr(demos, "write_dataset", _stop)
    out = run_bench(*ONE_CELL, "--results-dir", str(tmp_path / "results"), shared=False,
                    env={"GRAFTBENCH_QUIET": None, "GRAFTBENCH_CACHE": str(tmp_path / "cache")})
    assert "stand-in: the dataset is not written" in out.stdout, out.stdout[-3000:]
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("[graftbench] sim demos:")]
    assert lines, "no demonstration line on the terminal"
    scenes = [ln for ln in lines if ln.endswith(": building its scene")]  # before each make_env
    assert scenes == [f"[graftbench] sim demos: spatial task {t}: building its scene"
                      for t in range(4)]
    lines = [ln for ln in lines if ln not in scenes]
    assert lines[0] == ("[graftbench] sim demos: spatial: rendering 12 scripted demonstrations "
                        "(4 tasks x 3; a line per attempt)")
    attempts = lines[1:-1]
    assert len(attempts) == 13  # 4 tasks x 3 kept + task 1's failed first init state
    assert attempts[3].startswith("[graftbench] sim demos: spatial task 1 init 0: failure in 3 "
                                  "steps (0.1 s); kept 0/3; suite 3/12, ~")
    assert re.fullmatch(r".* kept 3/3; suite 12/12", attempts[-1])
    assert lines[-1] == ("[graftbench] sim demos: spatial: writing the kept episodes as a "
                         "LeRobotDataset")
    assert "sim demos" not in out.stderr  # on the terminal, not in the captured stderr
    # Inside the 40 s attempt: one line at 30 s (an attempt renders for up to a minute or two).
    within = [ln for ln in out.stdout.splitlines() if "task 0 init 0: step:" in ln]
    assert len(within) == 1 and re.fullmatch(
        r"\[graftbench\]   sim demos: spatial task 0 init 0: step: \d+/\d+ \(30s, ~\d+s left\)",
        within[0]), within
