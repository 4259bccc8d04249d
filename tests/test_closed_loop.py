"""The closed-loop controller runs the offline scoring path: same actions for the same noise.

No simulator needed: observations are held-out frames of the tiny suite, shaped as LIBERO's env
hands them over (images, state, task; no action keys).
"""

from __future__ import annotations

import json
from dataclasses import replace

from bench.progress import QUIET
import pytest
import torch

from bench.grid.cells import CellSpec
from bench.cell.rollouts import (
    NO_CLOSED_LOOP, LoopGraft, cell_act, make_act, observation_noise,
)
from bench.loops.encode import encode_pooled
from graftcore.graft import GraftFeed, Projector
from bench.suites.windows import raw_batch
from bench.loops.train import frozen_autocast
from tests.factories import make_record


def observations(ws, n=6):
    suite, split = ws.suite("spatial"), ws.split("spatial")
    raw = raw_batch(suite, split.windows[:n], 10)
    return {k: v for k, v in raw.items() if k not in ("action", "action_is_pad")}


def offline_actions(backbone, obs, noise, feed=None, features=None):
    """What bench.loops.evaluate.score computes for these windows, in raw units."""
    info = backbone.info
    raw = {**obs, "action": torch.zeros((len(obs["task"]), info.chunk_size, 7)),
           "action_is_pad": torch.zeros((len(obs["task"]), info.chunk_size), dtype=torch.bool)}
    batch = backbone.preprocess(raw)
    if feed is not None:
        feed.bind(features)
        with backbone.image_embedder(feed), frozen_autocast(torch.device("cpu")):
            pred = backbone.sample_actions(batch, noise)
    else:
        pred = backbone.sample_actions(batch, noise)
    return backbone.unnormalize_actions(pred[..., :7]).float()


@pytest.mark.parametrize("backbone_name", ["smolvla", "pi05"])
def test_native_act_is_the_offline_sampler_with_observation_noise(tiny_ws, backbone_name):
    backbone = tiny_ws.backbone(backbone_name)
    obs = observations(tiny_ws)
    act = make_act(backbone, noise_seed=3)
    out = act(obs)
    assert out.shape == (6, backbone.info.chunk_size, 7)
    noise = observation_noise(obs, backbone.info.chunk_size, backbone.info.max_action_dim, 3)
    torch.testing.assert_close(out, offline_actions(backbone, obs, noise))
    torch.testing.assert_close(act(obs), out, rtol=0, atol=0)  # deterministic, no counter
    # Row noise depends on the row's own observation only: a sub-batch gets the same rows.
    sub = {k: v[2:4] for k, v in obs.items()}
    torch.testing.assert_close(act(sub), out[2:4], rtol=1e-5, atol=1e-5)


def test_graft_act_encodes_live_pixels_like_the_feature_cache(tiny_ws):
    backbone = tiny_ws.backbone("pi05")
    encoder = tiny_ws.encoder("pixels")
    grid = backbone.info.native_grid
    torch.manual_seed(0)
    projector = Projector(encoder.channels, backbone.info.lm_width).eval()
    feed = GraftFeed(projector, backbone.camera_keys, grid)
    obs = observations(tiny_ws)
    cell = CellSpec("graft", "pi05", "spatial", 0, "pixels")
    out = cell_act(cell, backbone, noise_seed=1, graft=LoopGraft(feed, encoder, grid))(obs)
    noise = observation_noise(obs, backbone.info.chunk_size, backbone.info.max_action_dim, 1)
    frames = tiny_ws.split("spatial").windows[:6]
    stored, tiny_ws.feature_dtype = tiny_ws.feature_dtype, "float32"  # the encoder's own numbers
    try:
        cached = tiny_ws.features("pixels", "spatial", grid)
        expected = offline_actions(backbone, obs, noise, feed,
                                   {k: v[frames] for k, v in cached.items()})
    finally:
        tiny_ws.feature_dtype = stored
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)
    # zero_image cells see black frames in closed loop too: not the same actions.
    zero = CellSpec("zero_image", "pi05", "spatial", 0, "pixels", "eval")
    blank = cell_act(zero, backbone, noise_seed=1, graft=LoopGraft(feed, encoder, grid))(obs)
    zeros = encode_pooled(encoder, {k: torch.zeros_like(obs[k]) for k in backbone.camera_keys}, grid)
    torch.testing.assert_close(blank, offline_actions(backbone, obs, noise, feed, zeros),
                               rtol=1e-4, atol=1e-5)
    assert not torch.allclose(blank, out)


def test_missing_observation_keys_are_named(tiny_ws):
    act = make_act(tiny_ws.backbone("pi05"), noise_seed=0)
    obs = observations(tiny_ws, 2)
    del obs["observation.state"]
    with pytest.raises(KeyError, match="observation.state"):
        act(obs)


def test_resume_rule_for_rollouts():
    """bench.results.current resumes a record with --rollouts N only when it holds N episodes per
    task (or its kind's skip line)."""
    from bench.results.record import RunInfo

    assert not RunInfo().has_rollouts(5)
    assert RunInfo(rollouts={"spec": {"episodes_per_task": 5}}).has_rollouts(5)
    assert not RunInfo(rollouts={"spec": {"episodes_per_task": 2}}).has_rollouts(5)
    assert RunInfo(rollouts={"skipped": NO_CLOSED_LOOP["shuffled"]}).has_rollouts(5)


class Killed(BaseException):
    """A kill arriving mid-episode (not an Exception: nothing may catch and record it)."""


def fake_scenes(ws, kill_at_reset: int | None = None, crash_at_reset: int | None = None):
    """bench.sim.rollout.Scenes without the simulator, for the real rollout loop: observations
    are tiny-suite frames (the cell's policy runs on them for real); an episode succeeds at its
    3rd step, except task 0 from init state 48, which runs out its steps. Counts resets."""
    from bench.sim.rollout import Scenes

    frames, tasks, resets = observations(ws, 4), ws.suite("spatial").tasks, []

    class Env:
        def __init__(self, task):
            self.task, self.init, self.t = task, 0, 0

        def step(self, action):
            if crash_at_reset is not None and len(resets) >= crash_at_reset:
                raise RuntimeError("mj_step: simulation unstable (QACC)")
            self.t += 1
            won = self.t >= 3 and (self.task, self.init) != (0, 48)
            return self.init % 4, 0.0, False, False, {"is_success": won}

        def close(self):
            pass

    def reset_to(env, init_state, seed):
        resets.append((env.task, init_state))
        if kill_at_reset is not None and len(resets) >= kill_at_reset:
            raise Killed()
        env.init, env.t = init_state, 0
        return init_state % 4

    def observe(raws, texts):
        i = raws[0]
        return {**{k: v[i:i + 1] for k, v in frames.items() if k != "task"}, "task": list(texts)}

    scenes = Scenes(lambda suite, task, render, max_steps=None: Env(task), lambda suite: tasks,
                    lambda env: 50, reset_to, observe)
    return scenes, resets


def test_rollouts_resume_per_episode_after_a_kill(tiny_ws, tmp_path, monkeypatch):
    """Killed during its 4th episode, a cell keeps the 3 finished ones (atomically, in the
    store's episode log) and a rerun rolls out only the rest: same episodes as one sitting."""
    from bench.results.store import ResultStore
    from bench.cell.rollouts import cell_rollouts

    store = ResultStore(tmp_path / "res")
    cell, backbone = CellSpec("native", "pi05", "spatial", 0), tiny_ws.backbone("pi05")
    run = lambda scenes, policy="p1", progress=QUIET: cell_rollouts(  # noqa: E731
        cell, tiny_ws.suite("spatial"), backbone, 2, store=store, policy=policy,
        scenes=scenes, progress=progress)
    killed, _ = fake_scenes(tiny_ws, kill_at_reset=4)
    with pytest.raises(Killed):
        run(killed)
    log = json.loads((tmp_path / "res" / "rollouts" / f"{cell.id}.json").read_text())
    assert [(e["task"], e["episode"]) for e in log["episodes"]] == [(0, 0), (0, 1), (1, 0)]

    scenes, resets = fake_scenes(tiny_ws)
    lines = []  # a progress sink: inside `pytest bench` one line per episode as it ends
    monkeypatch.delenv("GRAFTBENCH_QUIET", raising=False)

    class Sink:
        line = staticmethod(lines.append)

    out = run(scenes, progress=Sink())
    assert resets == [(1, 48), (2, 49), (2, 48), (3, 49), (3, 48)]  # only the 5 not finished
    assert lines[0].startswith("[rollout] spatial task 1 episode 1 (init 48): success in 3 "
                               f"steps ({out['episodes'][3]['seconds']:.1f} s); episodes 4/8")
    assert len(lines) == 5 and lines[-1].endswith("; episodes 8/8")  # how far, resumed counted
    assert [(e["task"], e["episode"], e["init_state"]) for e in out["episodes"]] == [
        (t, e, 49 - e) for t in range(4) for e in range(2)]
    assert [e["success"] for e in out["episodes"]] == [True, False] + [True] * 6
    assert out["settings"]["resumed_episodes"] == 3 and out["success_rate"] == 7 / 8

    # Episodes of another policy are never resumed; writing the record removes the log.
    other, resets = fake_scenes(tiny_ws, kill_at_reset=2)
    with pytest.raises(Killed):
        run(other, policy="p2")
    assert resets == [(0, 49), (0, 48)]  # started over, not resumed from p1's episodes
    store.write(make_record(kind="native", backbone="pi05", encoder=None).replace(
        cell_id=cell.id))
    assert not (tmp_path / "res" / "rollouts" / f"{cell.id}.json").exists()


def test_a_crashed_env_fails_its_cell_with_the_reason_and_the_next_cell_runs(tiny_ws, tmp_path):
    from bench.results.record import Failure
    from bench.results.store import ResultStore
    from bench.cell.rollouts import cell_rollouts
    from bench.sim.rollout import RolloutCrashed

    store, suite = ResultStore(tmp_path / "res"), tiny_ws.suite("spatial")
    backbone = tiny_ws.backbone("pi05")
    broken = CellSpec("native", "pi05", "spatial", 0)
    crashing, _ = fake_scenes(tiny_ws, crash_at_reset=2)
    with pytest.raises(RolloutCrashed) as crash:
        cell_rollouts(broken, suite, backbone, 2, store=store, scenes=crashing, progress=QUIET)
    line = Failure.of(broken, "hash", crash.value).error
    assert line.startswith("RolloutCrashed: rollout crashed in spatial task 0 episode 1 (init "
                           "state 48): RuntimeError: mj_step: simulation unstable (QACC) (1 "
                           "episode(s) finished before it are kept; rerun to resume)"), line
    healthy, _ = fake_scenes(tiny_ws)
    other = CellSpec("native", "pi05", "spatial", 1)
    out = cell_rollouts(other, suite, backbone, 2, store=store, scenes=healthy, progress=QUIET)
    assert len(out["episodes"]) == 8


def test_the_episode_log_key_ignores_the_grid_files_text_not_what_it_measures():
    """A comment edited in a study's grid file between sittings restarted a resumed item's
    episodes (the key read the file's text); what the policy is measured under still counts."""
    from bench.cell.rollouts import policy_identity
    from tests.factories import make_record

    measured = make_record().measured
    noted = replace(measured, grid_file={"path": "s.toml", "sha256": "a", "text": "# one"})
    edited = replace(noted, grid_file={"path": "s.toml", "sha256": "b", "text": "# two"})
    assert policy_identity(noted) == policy_identity(edited)
    assert policy_identity(noted) != policy_identity(replace(noted, protocol_hash="other"))
    assert (policy_identity(noted, perturbation={"kind": "blur"})
            != policy_identity(noted, perturbation={"kind": "noise"}))
