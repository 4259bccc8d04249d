"""Offline measures beside the full-chunk MSE (bench.analysis.offline_measures): known answers on
planted records, the executed-steps and critical-window inputs scoring stores, and "not
measured" for records from before them."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from bench.analysis.agreement import Undefined, spearman_rho
from bench.analysis.offline_measures import MEASURES, executed_errors
from bench.analysis.rollouts import rollout_agreement
from bench.report.closed_loop import closed_loop_caveat, measure_verdict, measures_table
from bench.loops.evaluate import masked_sq_error, prefix_window_error
from bench.suites.critical import critical_rule, critical_windows
from tests.factories import make_record

N_WINDOWS, CHUNK = 24, 5
TASK_NAMES = {"3": "task 0: put the bowl 0", "7": "task 1: put the bowl 1"}  # factories' names


def episodes(rates: dict[int, float], per_task: int = 20) -> dict:
    """Rollouts whose first round(rate * per_task) episodes of each LIBERO task id succeed."""
    rows = [{"task": t, "episode": e, "init_state": 49 - e, "success": e < round(r * per_task),
             "steps": 50} for t, r in rates.items() for e in range(per_task)]
    return {"episodes": rows, "task_names": TASK_NAMES,
            "spec": {"n_action_steps": CHUNK, "episodes_per_task": per_task}}


def item(encoder: str, per_window, rate: float | dict, **fields):
    rates = rate if isinstance(rate, dict) else {3: rate, 7: rate}
    return make_record(encoder=encoder, per_window=list(per_window), chunk=CHUNK,
                       rollouts=episodes(rates), **fields)


def by_name(cl) -> dict:
    return {m.name: m for m in cl.measures}


CRITICAL = [i % 4 == 0 for i in range(N_WINDOWS)]  # 6 of 24 windows
NEW_FIELDS = dict(window_critical=CRITICAL, critical_rule=critical_rule(),
                  chunk_length=CHUNK, n_action_steps=CHUNK)


def test_errors_only_in_critical_windows_rank_worst_by_critical_not_by_full_chunk():
    # a: 0.1 off the critical windows, 0.5 on them (full 0.2); b: 0.25 flat; c: 0.15 flat.
    # Full chunk orders c < a < b, critical c < b < a; success c 0.9 > b 0.6 > a 0.2 (a fails
    # where it matters). Full-chunk tau-b: (c,a), (c,b) concordant, (a,b) discordant = 1/3.
    a = [0.5 if crit else 0.1 for crit in CRITICAL]
    cl = rollout_agreement([item("a", a, 0.2, **NEW_FIELDS),
                            item("b", [0.25] * N_WINDOWS, 0.6, **NEW_FIELDS),
                            item("c", [0.15] * N_WINDOWS, 0.9, **NEW_FIELDS)],
                           "smolvla", "spatial", n_resamples=60)
    full, critical = by_name(cl)["full chunk"], by_name(cl)["critical interval"]
    assert full.labels == critical.labels == ["a", "b", "c"]
    assert full.error == pytest.approx([0.2, 0.25, 0.15])
    assert critical.error == pytest.approx([0.5, 0.25, 0.15])
    assert np.argmax(critical.error) == 0 and np.argmax(full.error) != 0
    assert full.value["tau_b"] == pytest.approx(1 / 3)
    assert critical.value["tau_b"] == pytest.approx(1.0)
    assert critical.value["spearman_rho"] == pytest.approx(1.0)
    assert critical.value["mmrv"] == pytest.approx(0.0)
    assert "6 of 24 windows" in critical.note


def test_full_chunk_row_is_the_closed_loop_agreement_bit_for_bit():
    rng = np.random.default_rng(0)
    records = [item(e, 0.1 * (k + 1) + 0.05 * rng.random(N_WINDOWS), r, **NEW_FIELDS)
               for k, (e, r) in enumerate([("a", 0.8), ("b", 0.5), ("c", 0.6)])]
    cl = rollout_agreement(records, "smolvla", "spatial", n_resamples=40)
    full = by_name(cl)["full chunk"]
    for k in ("tau_b", "pearson_r", "mmrv", "top1_regret"):
        assert full.value[k] == cl.agreement[k]
        assert full.interval_of(k) == cl.interval_of(k)


def test_executed_steps_equal_full_chunk_when_n_action_steps_is_the_chunk():
    rng = np.random.default_rng(1)
    records = [item(e, 0.1 * (k + 1) + 0.2 * rng.random(N_WINDOWS), r, **NEW_FIELDS)
               for k, (e, r) in enumerate([("a", 0.8), ("b", 0.6), ("c", 0.3)])]
    m = by_name(rollout_agreement(records, "smolvla", "spatial", n_resamples=40))
    assert m["executed steps"].error == m["full chunk"].error
    assert m["executed steps"].value == m["full chunk"].value
    assert m["executed steps"].intervals == m["full chunk"].intervals
    assert m["executed steps"].note == "n_action_steps 5 of chunk 5 (the full chunk)"
    # Where it is scored: the prefix over every step is the per-window error, bit for bit.
    gen = torch.Generator().manual_seed(0)
    pred, target = torch.randn((6, CHUNK, 7), generator=gen), torch.randn((6, CHUNK, 7),
                                                                           generator=gen)
    valid = torch.ones((6, CHUNK), dtype=torch.bool)
    valid[0, 3:] = False  # a window near its episode's end: padded steps never count
    per_window, per_step = masked_sq_error(pred, target, valid)
    assert torch.equal(prefix_window_error(per_step, valid, CHUNK), per_window)


def test_executed_steps_reads_only_the_executed_prefix():
    # Known answer: per-step errors 1, 2, 3, 4, 5 (step 4 padded): first 2 steps -> 1.5.
    per_step = torch.tensor([[1.0, 2.0, 3.0, 4.0, 0.0]])
    valid = torch.tensor([[True, True, True, True, False]])
    assert prefix_window_error(per_step, valid, 2).item() == pytest.approx(1.5)
    assert prefix_window_error(per_step, valid, 5).item() == pytest.approx(2.5)
    # An item good over the whole chunk but bad over the executed steps ranks worst by them.
    fields = dict(NEW_FIELDS, n_action_steps=2)
    recs = []
    for enc, full, head, rate in (("a", 0.10, 0.40, 0.1), ("b", 0.20, 0.20, 0.5),
                                  ("c", 0.30, 0.10, 0.9)):
        r = item(enc, [full] * N_WINDOWS, rate, **fields,
                 per_window_executed={"normalized": [head] * N_WINDOWS,
                                      "raw": [2 * head] * N_WINDOWS})
        rollouts = dict(r.run.rollouts, spec={"n_action_steps": 2})
        recs.append(r.replace(rollouts=rollouts))
    m = by_name(rollout_agreement(recs, "smolvla", "spatial", n_resamples=40))
    assert m["executed steps"].error == pytest.approx([0.4, 0.2, 0.1])
    assert m["executed steps"].value["tau_b"] == pytest.approx(1.0)
    assert m["full chunk"].value["tau_b"] == pytest.approx(-1.0)
    assert m["executed steps"].note == "n_action_steps 2 of chunk 5"
    # The loop executed 2 steps but the record keeps no error over them: not measured.
    bare = recs[0].replace(per_window_executed=None)
    assert isinstance(executed_errors(bare), Undefined)


def test_per_task_agreement_over_item_x_task_pairs():
    # Pairs by -MSE: a/t3 (0.1, 0.8), b/t3 (0.2, 0.6), b/t7 (0.3, 0.3), a/t7 (0.4, 0.35).
    # Only (b/t7, a/t7) is discordant: tau-b (5 - 1) / 6 = 2/3; Spearman ranks of success
    # 4, 3, 1, 2 against 4, 3, 2, 1: 1 - 6 * 2 / (4 * 15) = 0.8; MMRV: that pair's 0.05 on two
    # of four rows = 0.025; the offline pick a/t3 has the best success: regret 0.
    a = [0.1 if i % 2 == 0 else 0.4 for i in range(N_WINDOWS)]  # factories: window i is task i%2
    b = [0.2 if i % 2 == 0 else 0.3 for i in range(N_WINDOWS)]
    cl = rollout_agreement([item("a", a, {3: 0.8, 7: 0.35}), item("b", b, {3: 0.6, 7: 0.3})],
                           "smolvla", "spatial", n_resamples=60)
    m = by_name(cl)["per task"]
    assert m.missing is None
    assert m.labels == ["a / task 3", "b / task 3", "a / task 7", "b / task 7"]
    assert m.error == pytest.approx([0.1, 0.2, 0.4, 0.3])
    assert m.success == pytest.approx([0.8, 0.6, 0.35, 0.3])
    assert m.value["tau_b"] == pytest.approx(2 / 3)
    assert m.value["spearman_rho"] == pytest.approx(0.8)
    assert m.value["mmrv"] == pytest.approx(0.025)
    assert m.value["top1_regret"] == pytest.approx(0.0)
    assert m.value["pearson_r"] == pytest.approx(np.corrcoef(-np.array(m.error), m.success)[0, 1])
    lo, hi = m.interval_of("spearman_rho")
    assert -1 <= lo <= hi <= 1
    # One held-out episode per task (the closed-loop study's split): each row reads its own
    # task's episode, so the draw keeps every task's; across tasks it would leave rows empty.
    one = dict(window_episode=[i % 2 for i in range(N_WINDOWS)])
    cl = rollout_agreement([item("a", a, {3: 0.8, 7: 0.35}, **one),
                            item("b", b, {3: 0.6, 7: 0.3}, **one)], "smolvla", "spatial",
                           n_resamples=60)
    assert all(by_name(cl)["per task"].interval_of(k) is not None
               for k in ("tau_b", "spearman_rho", "mmrv"))


def test_records_without_the_new_fields_leave_the_measures_not_measured():
    old = [make_record(encoder=e, per_window=[lvl] * N_WINDOWS, chunk=CHUNK,
                       rollouts={"episodes": episodes({3: r})["episodes"]})
           for e, lvl, r in (("a", 0.1, 0.8), ("b", 0.2, 0.5))]
    cl = rollout_agreement(old, "smolvla", "spatial", n_resamples=50)
    m = by_name(cl)
    assert [x.name for x in cl.measures] == [x.name for x in MEASURES]
    assert m["full chunk"].missing is None
    for name in ("executed steps", "critical interval", "per task"):
        assert m[name].missing and not m[name].value and not m[name].labels, name
    text = measures_table(cl)
    for name in ("executed steps", "critical interval", "per task"):
        row = next(line for line in text.splitlines() if line.startswith(f"| {name}"))
        assert "not measured" in row and " 0 " not in row


def test_critical_windows_by_the_rule():
    # Episode 0 (frames 0-19): gripper open, closes at 10, opens at 18: events 10 and 18.
    # Episode 1 (20-39): open throughout; its first frame is no event (another episode).
    grip = [-1.0] * 10 + [1.0] * 8 + [-1.0] * 2 + [-1.0] * 20
    action = torch.zeros((40, 7))
    action[:, 6] = torch.tensor(grip)
    suite = SimpleNamespace(action=action, episode_index=torch.tensor([0] * 20 + [1] * 20))
    windows = torch.arange(0, 40, 2)
    flags = critical_windows(suite, windows, chunk=3, margin=2)
    # Near frames: 8-12 and 16-19 (frame 20 is the next episode's); span s..s+2.
    assert windows[flags].tolist() == [6, 8, 10, 12, 14, 16, 18]
    # A user's dataset whose actions have no 7th (gripper) dimension: not measured, no error
    # (every cell of such a dataset failed on it once).
    six = SimpleNamespace(action=action[:, :6], episode_index=suite.episode_index)
    assert critical_windows(six, windows, chunk=3, margin=2) is None


def test_spearman_known_answer_and_ties():
    # Ranks of (1, 2, 2, 3) share 2.5: Pearson of (1, 2.5, 2.5, 4) and (1, 2, 3, 4) = 4.5 /
    # sqrt(4.5 * 5).
    assert spearman_rho([1, 2, 2, 3], [1, 2, 3, 4]) == pytest.approx(4.5 / (4.5 * 5) ** 0.5)
    assert isinstance(spearman_rho([1, 1, 1], [1, 2, 3]), Undefined)


def test_the_verdict_reads_a_measure_only_where_it_agrees_measurably_better():
    # a: 0.05 off the critical windows, 0.35 on them (full 0.125): the full chunk ranks it
    # first though it fails where it matters (success 0.2; b 0.25 flat, 0.6; c 0.15 flat, 0.9).
    # Full-chunk tau-b -1/3 (only (c, b) concordant), critical 1: +4/3. A replicate puts a
    # behind c by the full chunk when it draws over 1/3 critical windows (then +2/3), behind b
    # only above 2/3 (never): so the paired difference's interval lies above 0.
    a = [0.35 if crit else 0.05 for crit in CRITICAL]
    cl = rollout_agreement([item("a", a, 0.2, **NEW_FIELDS),
                            item("b", [0.25] * N_WINDOWS, 0.6, **NEW_FIELDS),
                            item("c", [0.15] * N_WINDOWS, 0.9, **NEW_FIELDS)],
                           "smolvla", "spatial", n_resamples=200)
    m = by_name(cl)
    assert m["full chunk"].versus_full is None
    assert m["critical interval"].versus_full == pytest.approx(4 / 3)
    assert m["critical interval"].versus_full_interval.high == pytest.approx(4 / 3)
    assert m["critical interval"].versus_full_interval.low > 0
    executed = m["executed steps"].versus_full_interval  # the same windows: exactly 0
    assert (executed.low, executed.high, m["executed steps"].versus_full) == (0.0, 0.0, 0.0)
    assert "not the items" in m["per task"].versus_full.reason
    verdict = measure_verdict(cl)
    assert verdict.startswith("Which offline measure to read: the **critical interval** MSE")
    assert "Which offline measure to read: the **critical interval**" in closed_loop_caveat(
        SimpleNamespace(closed_loop=[cl]))
    # The same items with the errors spread evenly: the critical interval agrees no better
    # than the full chunk, and the verdict keeps the full chunk.
    flat = rollout_agreement([item("a", [0.125] * N_WINDOWS, 0.2, **NEW_FIELDS),
                              item("b", [0.25] * N_WINDOWS, 0.6, **NEW_FIELDS),
                              item("c", [0.15] * N_WINDOWS, 0.9, **NEW_FIELDS)],
                             "smolvla", "spatial", n_resamples=200)
    assert by_name(flat)["critical interval"].versus_full == 0.0
    assert measure_verdict(flat).startswith(
        "Which offline measure to read: the **full chunk** MSE")


def test_rollouts_from_two_machines_kernels_are_named_in_the_caveats(tmp_path):
    from bench.report import build
    from bench.report.closed_loop import rollout_hardware
    from tests.test_report import write_grid

    avx512, avx2 = (f"CPU X ({k} kernels), 2 cores, torch threads 1" for k in ("AVX512", "AVX2"))
    records = [item("dinov2_s", np.full(N_WINDOWS, 0.1), 0.8, hardware=avx512),
               item("pixels", np.full(N_WINDOWS, 0.2), 0.3, hardware=avx512),
               make_record(encoder="blind", hardware=avx2)]  # no episodes: not a rollout
    assert rollout_hardware(records) == {}
    records.append(item("siglip_b", np.full(N_WINDOWS, 0.15), 0.5, hardware=avx2))
    assert rollout_hardware(records) == {
        avx2: ["smolvla-spatial-siglip_b-seed0"],
        avx512: ["smolvla-spatial-dinov2_s-seed0", "smolvla-spatial-pixels-seed0"]}
    text = build.build_report(write_grid(tmp_path / "report", records), tmp_path / "REPORT.md",
                              n_resamples=20, plots=False).read_text()
    assert (f"**Rollouts ran on 2 machines' kernels** ({avx2}: smolvla-spatial-siglip_b-seed0 "
            f"(1 cell(s)); {avx512}: smolvla-spatial-dinov2_s-seed0, "
            "smolvla-spatial-pixels-seed0 (2 cell(s)))") in text
