"""Closed-loop episodes over worker processes: the simulator on every core, the policy here.

`run_task_workers` hands the planned episodes to W spawned worker processes, each holding its
own LIBERO env per task (and its own EGL context). A worker resets its env, executes the action
chunks it is sent (bench.sim.episode.execute_chunk, frames rendered only where read) and sends
back the observation the policy reads; this process calls the policy, one observation at a
time, exactly as the in-process loop does (bench.sim.rollout.run_episode), so the actions, the
init states, env seeds and rows are the in-process ones (tests/test_sim_frames.py). The policy
is called here because it is the cheap part (one call per `n_action_steps` simulator steps) and
it stays loaded once. A finished worker takes the next planned episode at once.

The workers outlive a run: `kept_workers` keeps one pool per process, keyed by everything its
workers were started with, and lends it to the next run that asks for the same key (the next
cell of a `pytest bench` process), so the process start-up and the env builds (~6 s of CPU each)
are paid once per process, not per cell. An env is reset to each episode's init state and seed
whichever run it served before, as between the episodes of one run. A pool is stopped when
another key is asked for (before the new one starts: never two pools alive), when a run on it
raises (a worker that died, errored or was left mid-episode is never lent again), and at exit.
"""

from __future__ import annotations

import atexit
import multiprocessing as mp
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from typing import Callable, Iterator

import torch


@dataclass
class _Slot:
    """One worker and the episode it is running (None: idle)."""

    process: object
    conn: object
    episode: tuple | None = None  # (task, episode, env_seed)
    init_state: int | None = None  # the worker's answer to the reset
    steps: int = 0
    start: float = 0.0
    tasks: set = field(default_factory=set)  # tasks whose env the worker has built


def _to_numpy(raw: dict) -> dict:
    return {k: v if k == "task" else v.numpy() for k, v in raw.items()}


def _to_torch(raw: dict) -> dict:
    return {k: v if k == "task" else torch.from_numpy(v) for k, v in raw.items()}


def _serve(conn, scenes, suite: str, render, max_steps: int, descriptions: list[str]) -> None:
    """A worker: one env per task, built on first use; answers reset and chunk messages."""
    from bench.sim.episode import execute_chunk, rollout_init_state

    torch.set_num_threads(1)  # one core a worker; the parent's policy has one thread too
    envs = {}
    try:
        while True:
            message = conn.recv()
            try:
                if message[0] == "close":
                    return
                if message[0] == "envs":  # kept_workers' check before lending the pool again
                    conn.send(("envs", sorted(envs)))
                    continue
                if message[0] == "reset":
                    _, task, episode, env_seed = message
                    if task not in envs:
                        envs[task] = scenes.make_env(suite, task, render, max_steps=max_steps)
                    current = (envs[task], descriptions[task])
                    init_state = rollout_init_state(episode, scenes.num_init_states(current[0]))
                    obs = scenes.reset_to(current[0], init_state, env_seed)
                    raw = _to_numpy(scenes.observe([obs], [current[1]]))
                    conn.send(("obs", 0, False, raw, init_state))
                else:  # ("chunk", actions, steps_left)
                    _, actions, steps_left = message
                    obs, done, success = execute_chunk(current[0], actions, steps_left,
                                                    scenes.read_after)
                    read = not success and done == len(actions) and done < steps_left
                    raw = _to_numpy(scenes.observe([obs], [current[1]])) if read else None
                    conn.send(("obs", done, success, raw, None))
            except Exception as e:  # noqa: BLE001: the parent names the episode and fails it
                conn.send(("error", f"{type(e).__name__}: {e}", traceback.format_exc()))
    finally:
        for env in envs.values():
            env.close()


def start_workers(n: int, scenes, suite: str, render, max_steps: int,
                  descriptions: list[str]) -> list[_Slot]:
    """`n` spawned workers (spawn: a forked child would inherit this process's torch threads
    and GL state; LeRobot's own async LIBERO envs spawn too)."""
    context = mp.get_context("spawn")
    slots = []
    for _ in range(n):
        parent, child = context.Pipe()
        process = context.Process(target=_serve, daemon=True,
                                  args=(child, scenes, suite, render, max_steps, descriptions))
        process.start()
        child.close()
        slots.append(_Slot(process, parent))
    return slots


def stop_workers(slots: list[_Slot]) -> None:
    for slot in slots:
        try:
            slot.conn.send(("close",))
        except (BrokenPipeError, OSError):
            pass
    for slot in slots:
        slot.process.join(timeout=30)
        if slot.process.is_alive():
            slot.process.terminate()
            slot.process.join(timeout=5)


@dataclass
class _Pool:
    key: tuple  # kept_workers' arguments
    slots: list[_Slot]


_kept: _Pool | None = None  # this process's pool, between runs


@contextmanager
def kept_workers(n: int, scenes, suite: str, render, max_steps: int,
                 descriptions: list[str]) -> Iterator[list[_Slot]]:
    """This process's `n` workers for these arguments: the kept pool when it was started with
    them and every worker answers, else a fresh one (the old one stopped first). Kept after the
    block; stopped if the block raises, since a worker may then be dead, failed, or mid-episode
    with a reply unread."""
    global _kept
    key = (n, scenes, suite, render, max_steps, tuple(descriptions))
    if _kept is not None and (_kept.key != key or not _answers(_kept.slots)):
        discard_workers()
    if _kept is None:
        _kept = _Pool(key, start_workers(n, scenes, suite, render, max_steps, descriptions))
    try:
        yield _kept.slots
    except BaseException:
        discard_workers()
        raise


def kept_pool() -> _Pool | None:
    """The pool kept for the next run (None: none is)."""
    return _kept


@atexit.register  # registered after multiprocessing's own: runs first, while pipes are open
def discard_workers() -> None:
    """Stop the kept pool, if any: the next run starts a fresh one."""
    global _kept
    pool, _kept = _kept, None
    if pool is not None:
        stop_workers(pool.slots)


def _answers(slots: list[_Slot], timeout: float = 60.0) -> bool:
    """Is every worker alive, its pipe empty, and holding the envs this process thinks it has?
    An idle worker answers at once; anything else (a stale reply, a dead pipe) fails."""
    for slot in slots:
        try:
            if not slot.process.is_alive() or slot.conn.poll():
                return False
            slot.conn.send(("envs",))
            if not slot.conn.poll(timeout) or slot.conn.recv() != ("envs", sorted(slot.tasks)):
                return False
        except (EOFError, OSError):
            return False
    return True


def run_workers(act, planned: list[tuple], slots: list[_Slot], spec,
                ended: Callable[[dict], None], crash: Callable) -> None:
    """Run every planned (task, episode, env_seed) on the workers; `ended(row)` as
    each finishes (rows as bench.sim.rollout.run_episode's, plus task and episode). `crash(step,
    where)` runs `step` and names the episode if it raises."""
    from bench.sim.episode import episode_row, next_actions

    queue = list(planned)

    def assign(slot: _Slot) -> None:
        nxt = next_episode(queue, slot.tasks)
        slot.episode, slot.steps, slot.init_state = nxt, 0, None
        if slot.episode is not None:
            slot.tasks.add(slot.episode[0])
            slot.start = time.perf_counter()
            slot.conn.send(("reset", *slot.episode))

    for slot in slots:
        assign(slot)
    while any(slot.episode is not None for slot in slots):
        by_conn = {slot.conn: slot for slot in slots if slot.episode is not None}
        for conn in wait(list(by_conn)):
            slot = by_conn[conn]
            task, episode, _ = slot.episode
            where = f"{spec.suite} task {task} episode {episode} (init state {slot.init_state})"
            _, done, success, raw, init_state = crash(lambda: _reply(slot), where)
            if init_state is not None:
                slot.init_state = init_state
                where = f"{spec.suite} task {task} episode {episode} (init state {init_state})"
            slot.steps += done
            if success or slot.steps >= spec.max_steps:
                ended({"task": task, "episode": episode,
                       **episode_row(slot.init_state, success, slot.steps, slot.start)})
                assign(slot)
                continue
            actions = crash(lambda: next_actions(act, _to_torch(raw), spec.n_action_steps),
                            where)
            slot.conn.send(("chunk", actions, spec.max_steps - slot.steps))


def next_episode(queue: list[tuple], tasks: set) -> tuple | None:
    """Pop the next episode for a worker holding envs of `tasks`: the first of a task it has
    (an env build is seconds), else the first of the task with the most episodes left (so
    that W workers start on W different tasks when there are as many)."""
    if not queue:
        return None
    mine = [i for i, planned in enumerate(queue) if planned[0] in tasks]
    if not mine:
        left = {}
        for planned in queue:
            left[planned[0]] = left.get(planned[0], 0) + 1
        busiest = max(left, key=lambda t: (left[t], -list(left).index(t)))
        mine = [i for i, planned in enumerate(queue) if planned[0] == busiest]
    return queue.pop(mine[0])


def _reply(slot: _Slot) -> tuple:
    """The worker's answer; its exception, or its death, raised here."""
    try:
        message = slot.conn.recv()
    except EOFError:
        raise RuntimeError(f"rollout worker {slot.process.pid} died (exit code "
                           f"{slot.process.exitcode}): a crash in the simulator") from None
    if message[0] == "error":
        raise RuntimeError(f"{message[1]} (in the worker: {message[2].strip().splitlines()[-3:]})")
    return message
