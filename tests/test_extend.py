"""More closed-loop episodes for a stored cell (bench.cell.extend): a record that stands for the
run in all but its episode count keeps its episodes and rolls out only the missing ones, with
the policy rebuilt from the store; anything else is measured again."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from bench.cell.extend import rebuilds_policy, rebuilt_graft
from bench.cell.plan import plan
from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY
from bench.results.current import RunConditions
from tests.factories import make_record
from tests.test_closed_loop import fake_scenes, observations

NATIVE = CellSpec("native", "pi05", "spatial", 0)


def stored_native(episodes_per_task: int | None):
    rollouts = None if episodes_per_task is None else {
        "spec": {"episodes_per_task": episodes_per_task},
        "episodes": [{"task": 0, "episode": e, "success": True} for e in range(episodes_per_task)]}
    return make_record(kind="native", backbone="pi05", encoder=None).replace(
        cell_id=NATIVE.id, rollouts=rollouts)


@pytest.mark.parametrize("stored_per_task, wanted, outcome", [
    (2, 3, "extend"), (None, 3, "extend"),  # fewer episodes, or none: keep them, roll the rest
    (3, 3, "resume"), (4, 3, "measure"),  # more than asked is another measurement
])
def test_the_plan_extends_only_a_record_with_fewer_episodes(stored_per_task, wanted, outcome):
    run = RunConditions(protocol_hash=TINY.protocol.hash, rollouts=wanted)
    got = plan(NATIVE, stored_native(stored_per_task), run, rebuilds=lambda cell, record: True)
    assert outcome == ("resume" if got.resume else "extend" if got.extend else "measure")


def test_another_protocol_or_a_policy_the_store_cannot_rebuild_is_measured_again(tmp_path):
    stored = stored_native(2)
    other = RunConditions(protocol_hash="another", rollouts=3)
    assert plan(NATIVE, stored, other, rebuilds=lambda c, r: True).extend is None
    run = RunConditions(protocol_hash=TINY.protocol.hash, rollouts=3)
    assert plan(NATIVE, stored, run, rebuilds=lambda c, r: False).extend is None
    assert rebuilds_policy(NATIVE, stored, tmp_path)  # trains nothing: always rebuilt
    lora = CellSpec("lora", "pi05", "spatial", 0, "pixels")
    graft = CellSpec("graft", "pi05", "spatial", 0, "pixels")
    named = make_record(backbone="pi05", encoder="pixels").replace(
        projector_file="projectors/x.safetensors", projector_sha256="0" * 64)
    assert not rebuilds_policy(lora, named, tmp_path)  # its adapters are not stored
    assert not rebuilds_policy(graft, named, tmp_path)  # the file named is absent
    (tmp_path / "projectors").mkdir()
    (tmp_path / "projectors" / "x.safetensors").write_bytes(b"")
    assert rebuilds_policy(graft, named, tmp_path)


def test_a_stored_cell_rolls_out_only_its_missing_episodes(tmp_path, monkeypatch):
    """Through the cell service, as `pytest bench --rollouts 3` on a record of 2 per task: the
    8 stored episodes are kept, 4 rolled out (one per task, init state 47), the offline scores
    untouched, the rows in one sitting's order."""
    from dataclasses import asdict

    from bench.cell.rollouts import rollout_spec, suite_render
    from bench.cell.service import CellService, RunSettings
    from bench.loops.evaluate import executed_steps
    from bench.results.store import ResultStore
    from tests.worlds import lent_workspace

    store = ResultStore(tmp_path / "res")
    ws = lent_workspace(TINY, store, rollouts=3)
    scenes, resets = fake_scenes(ws)
    monkeypatch.setattr("bench.sim.rollout.LIBERO", scenes)
    # The stored 2 per task, as a sitting of 2 leaves them (written here: rolling them out
    # would cost a 280-step episode)
    suite = ws.suite("spatial")
    spec = rollout_spec(suite, 2, executed_steps(ws.backbone("pi05", "spatial")),
                        scenes.descriptions)
    two = {"spec": asdict(spec), "settings": {"render": suite_render(suite).as_dict()},
           "episodes": [{"task": t, "episode": e, "init_state": 49 - e, "success": e == 0,
                         "steps": 3 if e == 0 else 280, "seconds": 1.0}
                        for t in range(4) for e in range(2)]}
    stored = make_record(kind="native", backbone="pi05", encoder=None).replace(
        cell_id=NATIVE.id, rollouts=two, checkpoint={
            **ws.checkpoint("pi05", "spatial"),
            "normalizer_fingerprint": ws.normalizer("pi05", "spatial").fingerprint})
    store.write(stored)
    resets.clear()
    service = CellService(TINY, store, lambda: ws,
                          RunSettings(feature_dtype=ws.feature_dtype, rollouts=3))
    record = service.run(NATIVE)
    assert resets == [(t, 47) for t in range(4)]

    def rows(out):
        return [(e["task"], e["episode"], e["init_state"], e["success"], e["steps"])
                for e in out["episodes"]]

    written = store.load(NATIVE.id)
    assert written.scores == stored.scores
    assert rows(written.run.rollouts) == rows(record.run.rollouts)
    # One sitting's rows: task-major, episode e from init state 49 - e, the 8 stored unchanged
    assert [r[:3] for r in rows(record.run.rollouts)] == [
        (t, e, 49 - e) for t in range(4) for e in range(3)]
    assert [r for r in rows(record.run.rollouts) if r[1] < 2] == rows(two)
    settings = record.run.rollouts["settings"]
    assert (settings["resumed_episodes"], settings["extended_from"]) == (8, 2)


def test_a_graft_rebuilt_from_its_stored_projector_is_the_same_policy(tiny_ws, tmp_path):
    """The same fingerprint (an episode log in flight resumes) and the same actions."""
    from bench.cell.projectors import save_projector
    from bench.cell.rollouts import LoopGraft, cell_act, policy_fingerprint, policy_identity
    from bench.cell.runner import cell_inputs
    from bench.results.store import ResultStore
    from graftcore.graft import GraftFeed, Projector

    ws = replace(tiny_ws, store=ResultStore(tmp_path / "res"))
    cell = CellSpec("graft", "pi05", "spatial", 0, "pixels")
    backbone, encoder = ws.backbone("pi05"), ws.encoder("pixels")
    grid = backbone.info.native_grid
    torch.manual_seed(0)
    feed = GraftFeed(Projector(encoder.channels, backbone.info.lm_width).eval(),
                     backbone.camera_keys, grid)
    file, sha = save_projector(ws.store.root, cell.id, feed.projector)
    record = make_record(backbone="pi05", encoder="pixels").replace(
        cell_id=cell.id, projector_file=file, projector_sha256=sha)
    inputs = cell_inputs(cell, ws.profile.protocol, ws.suite("spatial"), ws.split("spatial"),
                         backbone, torch.device("cpu"))
    rebuilt = rebuilt_graft(cell, ws, backbone, inputs, record)
    identity = policy_identity(record.measured)
    assert policy_fingerprint(backbone, rebuilt.feed, identity) == \
        policy_fingerprint(backbone, feed, identity)
    obs = observations(ws, 2)
    original = cell_act(cell, backbone, noise_seed=0, graft=LoopGraft(feed, encoder, grid))(obs)
    torch.testing.assert_close(cell_act(cell, backbone, noise_seed=0, graft=rebuilt)(obs),
                               original, rtol=0, atol=0)
