"""The protocol's data-sized numbers against the suites' data, at start-up: held-out episodes per
task below the episodes each task has (above it, the split fails inside every cell with a long
traceback), and the batch within the training frames (above them, every step silently took all
of them: a 10^9 batch started a release's 86-minute retraining).

What a suite holds is read without loading it (no LeRobot import, no frame read):
- generated tiny suites: their generator's parameters (bench.suites.synthetic.SUITE_PARAMS);
- simulated suites: their DemoSpec (tasks, episodes per task, the episode step limit);
- hub suites and --dataset folders: meta/info.json when the folder is on this machine
  (total_episodes / total_tasks is the MEAN per task; the fewest a task has is at most that,
  so a held-out count >= the mean always fails and is refused; a count below it is left to
  the split). A suite found nowhere is left to the preflight and the cell.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pytest


@dataclass(frozen=True)
class SuiteSize:
    """What a suite holds, as far as it is known before loading it."""

    episodes_per_task: float  # exact (generated suites), or the mean per task (info.json)
    exact: bool  # episodes_per_task is every task's count, not a mean
    max_frames_per_episode: int | None  # None: unknown; total_frames bounds the frames instead
    total_frames: int | None
    where: str  # where the numbers come from, for the message


def suite_size(profile, suite: str) -> SuiteSize | None:
    """The size of `suite` in `profile`'s world, or None when it cannot be known unloaded."""
    datasets = dict(profile.datasets)
    if suite in datasets:
        return _from_info(Path(datasets[suite]).expanduser(), f"--dataset {suite}")
    if profile.data_source == "tiny":
        from bench.suites.synthetic import SUITE_PARAMS

        params = SUITE_PARAMS.get(suite)
        if params is None:
            return None
        return SuiteSize(params["episodes_per_task"], True, params["max_len"], None,
                         f"the generated tiny suite {suite!r}")
    if profile.data_source == "sim":
        from bench.sim.demos import DEFAULT_SPECS, demo_spec

        if suite not in DEFAULT_SPECS:
            return None
        spec = demo_spec(suite, profile.sim_tasks, profile.sim_demos)
        return SuiteSize(spec.episodes_per_task, True, spec.max_steps, None,
                         f"the simulated suite {suite!r} (--sim-demos)")
    from bench.suites import libero

    try:
        local = libero.locate(libero._repo_id(suite), None, libero.LIBERO_REVISIONS.get(suite))
    except ValueError:
        return None
    return _from_info(local, f"LIBERO suite {suite!r}") if local is not None else None


def _from_info(folder: Path, what: str) -> SuiteSize | None:
    try:
        info = json.loads((folder / "meta" / "info.json").read_text())
        episodes, tasks = int(info["total_episodes"]), int(info["total_tasks"])
        frames = int(info["total_frames"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if tasks < 1:
        return None
    return SuiteSize(episodes / tasks, False, None, frames, f"{what} ({folder}/meta/info.json)")


def check_data_bounds(profile) -> None:
    """A UsageError (one line: where the value came from, the value, the suite's count and the
    fix) when heldout_episodes_per_task or batch_size cannot fit a selected suite."""
    p = profile.protocol
    where = (f"{profile.grid_file.path} [protocol]" if profile.grid_file is not None
             else f"profile {profile.name}")
    for suite in profile.suites:
        size = suite_size(profile, suite)
        if size is None:
            continue
        held = p.heldout_episodes_per_task
        if held >= size.episodes_per_task:
            has = (f"{size.episodes_per_task:g} episodes per task" if size.exact else
                   f"{size.episodes_per_task:.3g} episodes per task on average")
            most = max(1, int(-(-size.episodes_per_task // 1)) - 1)
            raise pytest.UsageError(
                f"{where}: heldout_episodes_per_task = {held}: {size.where} has {has}, and each "
                f"task needs at least one left to train on; give heldout_episodes_per_task <= "
                f"{most}")
        frames = training_frames(size, held, suite, profile)
        if frames is not None and p.batch_size > frames:
            raise pytest.UsageError(
                f"{where}: batch_size = {p.batch_size}: {size.where} has at most {frames} "
                f"training frames, so every step would take them all; give batch_size <= "
                f"{frames} (the study's is 8)")


def training_frames(size: SuiteSize, held: int, suite: str, profile) -> int | None:
    """An upper bound on the frames the training episodes hold (None: unknown)."""
    if size.exact and size.max_frames_per_episode is not None:
        tasks = _task_count(suite, profile)
        train_episodes = tasks * (size.episodes_per_task - held)
        return int(train_episodes * size.max_frames_per_episode)
    return size.total_frames


def _task_count(suite: str, profile) -> int:
    if profile.data_source == "sim":
        from bench.sim.demos import demo_spec

        return len(demo_spec(suite, profile.sim_tasks, profile.sim_demos).tasks)
    return 4  # bench.suites.synthetic.episodes draws 4 tasks
