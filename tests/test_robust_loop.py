"""The robustness tier in closed loop (bench.robust.closed_loop): known answers through the real
rollout loop and the cells' real policies, LIBERO replaced by tests/test_closed_loop.py's
stand-in scenes (tiny-suite frames; an episode succeeds at its 3rd step), so no simulator.

Known answers: a perturbation at severity 0 rolls out the clean rollouts' very actions and
episodes, and `blind` (features that ignore the image) does under brightness:3 too; the
perturbation reaches the frames the policy sees (brightness:3: the clean frames x 0.4); a draw
per frame makes a rerun identical (noise:3); the report puts the perturbed success beside the
clean one with Wilson intervals.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY, with_overrides
from bench.robust.perturbations import parse_robustness
from bench.robust.rescore import measure_robust
from bench.cell.service import run_cell
from tests.test_closed_loop import fake_scenes

FEW_STEPS = with_overrides(TINY, steps=12)
BACKBONE = "smolvla"
IMAGE = "observation.images.image"


@pytest.fixture(scope="module")
def loop_world(tmp_path_factory):
    """A tiny world rolling out 1 episode per task in stand-in scenes that record every action
    stepped; the cells (native, blind graft) measured with their clean rollouts."""
    from bench.results.store import ResultStore
    from bench.sim import rollout
    from tests.worlds import lent_workspace

    ws = lent_workspace(FEW_STEPS, ResultStore(tmp_path_factory.mktemp("loop")), rollouts=1)
    base, _ = fake_scenes(ws)
    stepped: list[np.ndarray] = []

    def recording(*args, **kwargs):
        env = base.make_env(*args, **kwargs)
        step = env.step
        env.step = lambda action: (stepped.append(np.array(action)), step(action))[1]
        return env

    scenes = dataclasses.replace(base, make_env=recording)
    mp = pytest.MonkeyPatch()
    mp.setattr(rollout, "LIBERO", scenes)  # the cells' own clean rollouts go there too
    records = {}
    try:
        for kind, encoder in (("native", None), ("graft", "blind")):
            spec = CellSpec(kind, BACKBONE, "spatial", 0, encoder)
            stepped.clear()
            records[spec.id] = (spec, run_cell(spec, ws), list(stepped))
        yield ws, records, stepped
    finally:
        mp.undo()


def rolled(ws, spec, labels, stepped, **kw):
    """measure_robust with 1 episode per task under `labels`; (record, actions stepped)."""
    stepped.clear()
    robust, _ = measure_robust(spec, ws, parse_robustness(labels, "test"), rollouts=1, **kw)
    return robust, list(stepped)


def episodes(rollouts):
    return [{k: v for k, v in e.items() if k != "seconds"} for e in rollouts["episodes"]]


def test_severity_zero_and_blind_roll_out_the_clean_actions(loop_world):
    ws, records, stepped = loop_world
    spec, record, clean = records[f"{BACKBONE}-spatial-native-seed0"]
    assert len(clean) == 12 and record.run.rollouts["success_rate"] == 1.0  # 4 tasks x 3 steps
    robust, actions = rolled(ws, spec, ["brightness:0"], stepped)
    assert np.array_equal(np.stack(actions), np.stack(clean))  # bit for bit
    assert episodes(robust.rollouts["brightness:0"]) == episodes(record.run.rollouts)
    robust, dimmed = rolled(ws, spec, ["brightness:0", "brightness:3"], stepped)
    assert len(dimmed) == 12 and not np.allclose(np.stack(dimmed), np.stack(clean))
    assert list(robust.rollouts) == ["brightness:0", "brightness:3"]  # brightness:0 resumed
    spec, record, clean = records[f"{BACKBONE}-spatial-blind-seed0"]
    _, actions = rolled(ws, spec, ["brightness:3"], stepped)
    assert np.array_equal(np.stack(actions), np.stack(clean))  # its features ignore the image


def test_the_perturbation_reaches_the_frames_the_policy_sees_and_reruns_identically(loop_world):
    ws, records, stepped = loop_world
    spec = records[f"{BACKBONE}-spatial-native-seed0"][0]
    backbone = ws.backbone(BACKBONE, "spatial")
    seen, preprocess = [], backbone.preprocess

    def spy(raw):
        if len(raw["task"]) == 1:  # a rollout's observation, not the offline rescoring's batch
            seen.append(raw[IMAGE].clone())
        return preprocess(raw)

    backbone.preprocess = spy
    try:
        rolled(ws, spec, ["brightness:0"], stepped, rerun=True)
        clean = seen[:]
        seen.clear()
        rolled(ws, spec, ["brightness:3"], stepped, rerun=True)
        dimmed = seen[:]
        seen.clear()
        _, noisy = rolled(ws, spec, ["noise:3"], stepped, rerun=True)
        first = seen[:]
        seen.clear()
        _, again = rolled(ws, spec, ["noise:3"], stepped, rerun=True)
    finally:
        backbone.preprocess = preprocess
    assert len(dimmed) == len(clean) == 4  # one policy call per episode
    for c, d in zip(clean, dimmed):  # the gain of brightness:3, on what the policy reads
        torch.testing.assert_close(d, c * 0.4, rtol=0, atol=1e-6)
    assert not torch.equal(first[0], clean[0])
    assert all(torch.equal(a, b) for a, b in zip(first, seen))  # a fixed draw per frame
    assert np.array_equal(np.stack(noisy), np.stack(again))


def test_the_report_puts_the_perturbed_success_beside_the_clean(loop_world):
    from bench.analysis.robust_loop import closed_loop_rows
    from bench.report.robustness import _closed_loop_text
    from bench.results.robust import load_all_robust

    ws, records, stepped = loop_world
    spec, record, _ = records[f"{BACKBONE}-spatial-native-seed0"]
    rolled(ws, spec, ["brightness:3"], stepped)
    (row,) = [r for r in closed_loop_rows([record], load_all_robust(ws.store.root)[0])]
    assert row.clean.successes == row.clean.episodes == 4 and row.lost["brightness:3"] == 0
    text = _closed_loop_text([row])
    assert "| clean " in text and "4/4 = 100% [51%, 100%]" in text


def test_native_and_the_best_graft_roll_out(tmp_path):
    from bench.results.store import ResultStore
    from bench.robust.closed_loop import best_graft_encoder, rolls_out
    from tests.factories import make_record

    profile = dataclasses.replace(FEW_STEPS, backbones=(BACKBONE,), suites=("spatial",),
                                  encoders=("blind", "pixels"), seeds=(0, 1))
    store = ResultStore(tmp_path)
    for encoder, seed, level in (("blind", 0, 0.2), ("pixels", 0, 0.1), ("pixels", 1, 0.4)):
        store.write(make_record(encoder=encoder, seed=seed, level=level))
    assert best_graft_encoder(profile, store, BACKBONE, "spatial") == "blind"  # 0.2 < 0.25
    assert rolls_out(CellSpec("native", BACKBONE, "spatial", 0), profile, store)
    assert rolls_out(CellSpec("graft", BACKBONE, "spatial", 1, "blind"), profile, store)
    assert not rolls_out(CellSpec("graft", BACKBONE, "spatial", 0, "pixels"), profile, store)
    assert not rolls_out(CellSpec("native_wrapped", BACKBONE, "spatial", 0), profile, store)


def _robust(record, label_mse: dict, label_success: dict, windows: list[int]):
    """A robustness record of `record` under each "kind:severity": per-window perturbed MSE
    `label_mse[label]` (flat) and the first round(rate * 10) episodes of each task succeeding."""
    from bench.results.robust import RobustEntry, RobustRecord, base_of

    entries, rollouts = [], {}
    for label, level in label_mse.items():
        kind, severity = label.split(":")
        entries.append(RobustEntry({"kind": kind, "severity": int(severity), "params": {},
                                    "seed": 0, "version": "1"}, {"normalized": level},
                                   {"normalized": [level] * len(windows)}))
        rollouts[label] = {"episodes": [
            {"task": t, "episode": e, "init_state": 49 - e,
             "success": e < round(label_success[label] * 10), "steps": 50}
            for t in (3, 7) for e in range(10)]}
    return RobustRecord(record.cell_id, record.kind, record.backbone, record.suite,
                        record.encoder, record.seed, base_of(record), windows, entries,
                        rollouts=rollouts)


def test_the_offline_robustness_order_against_the_closed_loop_one():
    # Known answer: under brightness:3 the graft's perturbed MSE (0.3, both seeds) is above
    # native's (0.2) and its perturbed success (0.1) below native's (0.6): the offline order
    # predicts the closed loop's (tau-b +1); under camera_shift:2 the graft's MSE is lower
    # (0.15 < 0.25) but its success lower too (0.2 < 0.5): tau-b -1. The intervals draw the
    # graft's two seeds, the windows and the episodes; flat scores leave them at the point.
    from bench.analysis.robust_loop import robust_orders
    from bench.report.robustness import _orders_text
    from tests.factories import make_record
    from tests.test_offline_measures import episodes

    rows = [make_record(kind="native", backbone="pi05", encoder=None, level=0.1,
                        rollouts=episodes({3: 0.8, 7: 0.8}, per_task=10))]
    rows += [make_record(backbone="pi05", encoder="effnet_lite2", seed=s, level=0.09,
                         rollouts=episodes({3: 0.7, 7: 0.7}, per_task=10)) for s in (0, 1)]
    windows = rows[0].scores.window_ids[::3]
    robust = [_robust(rows[0], {"brightness:3": 0.2, "camera_shift:2": 0.25},
                      {"brightness:3": 0.6, "camera_shift:2": 0.5}, windows)]
    robust += [_robust(r, {"brightness:3": 0.3, "camera_shift:2": 0.15},
                       {"brightness:3": 0.1, "camera_shift:2": 0.2}, windows) for r in rows[1:]]
    orders = {o.label: o for o in robust_orders(rows, robust, n_resamples=50)}
    bright, shift = orders["brightness:3"], orders["camera_shift:2"]
    assert bright.items == ["effnet_lite2", "native"]
    assert bright.seeds == {"effnet_lite2": [0, 1], "native": [0]}
    assert bright.mse == pytest.approx([0.3, 0.2]) and bright.success == pytest.approx([0.1, 0.6])
    assert bright.clean_success == pytest.approx([0.7, 0.8])
    assert bright.clean_mse == pytest.approx([0.09, 0.1], abs=0.02)  # the windows' own mean
    assert bright.episodes == [40, 20]
    assert bright.tau_b == 1.0 and (bright.interval.low, bright.interval.high) == (1.0, 1.0)
    assert shift.tau_b == -1.0 and (shift.interval.low, shift.interval.high) == (-1.0, -1.0)
    text = _orders_text([bright, shift])
    assert "| brightness:3 | effnet_lite2 | 0, 1" in " ".join(text.split())
    assert "0.3 (x" in text and "70% -> 10%" in text and "1 [1, 1]" in text
    assert "-1 [-1, -1]" in text
    # A stale robustness record (another projector) is left out, never mixed in.
    stale = dataclasses.replace(robust[1], base={**robust[1].base, "projector_sha256": "0" * 64})
    left = {o.label: o for o in robust_orders(rows, [robust[0], stale, robust[2]],
                                              n_resamples=20)}
    assert left["brightness:3"].seeds == {"effnet_lite2": [1], "native": [0]}
