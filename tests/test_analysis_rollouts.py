"""Closed-loop analysis on hand-made records: known rank agreement, intervals, pairing checks."""

from __future__ import annotations

import re

import numpy as np
import pytest

from bench.analysis.agreement import Undefined, pearson_r
from bench.analysis.two_axes import bootstrap_two_axes
from bench.analysis.rollouts import closed_loop_all, rollout_agreement
from bench.grid.kinds import record_label
from bench.stats import wilson_interval
from tests.factories import make_record
from bench.report.build import build_report


def rollouts(rate: float, n_tasks: int = 2, per_task: int = 10, init_offset: int = 0,
             scatter: int | None = None) -> dict:
    """Episodes whose first round(rate * per_task) of each task succeed; with `scatter` (a seed)
    those successes land on randomly chosen episodes instead."""
    k = round(rate * per_task)
    order = np.arange(per_task) if scatter is None else \
        np.random.default_rng(scatter).permutation(per_task)
    episodes = [{"task": t, "episode": e, "init_state": e + init_offset,
                 "success": bool(order[e] < k), "steps": 50}
                for t in range(n_tasks) for e in range(per_task)]
    return {"episodes": episodes, "success_rate": k / per_task}


def cells(levels_and_rates: dict[str, tuple[float, float]], seeds=(0, 1), noise=0.002,
          scatter: int | None = None, **kw) -> list[dict]:
    """Graft records with rollouts; `scatter` draws each cell's successful episodes at random."""
    return [make_record(encoder=enc, seed=s, level=level, noise=noise, rollouts=rollouts(
                rate, scatter=None if scatter is None else scatter + 10 * i + s, **kw))
            for i, (enc, (level, rate)) in enumerate(levels_and_rates.items()) for s in seeds]


def test_agreeing_rankings_give_tau_one_and_reversed_minus_one():
    same = rollout_agreement(cells({"a": (0.10, 0.9), "b": (0.20, 0.6), "c": (0.30, 0.2)}),
                             "smolvla", "spatial", n_resamples=200)
    assert same.missing is None
    assert same.items == ["a", "b", "c"]
    assert same.agreement["tau_b"] == pytest.approx(1.0)
    assert same.agreement["mmrv"] == pytest.approx(0.0)
    assert same.success == pytest.approx([0.9, 0.6, 0.2])
    assert same.n_episodes == [40, 40, 40]  # 2 seeds x 2 tasks x 10 episodes
    lo, hi = same.interval_of("tau_b")
    assert lo <= 1.0 <= hi + 1e-12 and lo > 0  # clearly separated items: interval above 0

    reversed_ = rollout_agreement(cells({"a": (0.10, 0.2), "b": (0.20, 0.6), "c": (0.30, 0.9)}),
                                  "smolvla", "spatial", n_resamples=200)
    assert reversed_.agreement["tau_b"] == pytest.approx(-1.0)
    assert reversed_.interval_of("tau_b")[1] < 0
    assert reversed_.agreement["pearson_r"] < -0.9


# Hand-worked: MSE a < b < c < d (offline order a, b, c, d); success 0.6, 0.6, 0.2, 0.4 (a and
# b tie in closed loop). Pairs (6): ab tied on success -> neither; ac, ad, bc, bd concordant; cd
# discordant: tau-b = (4 - 1) / sqrt(6 * 5) = 0.5477. MMRV (SimplerEnv, success units): a: ab
# is a violation (offline separates, closed loop ties) costing |0.6 - 0.6| = 0; b: none; c and
# d: the cd violation, 0.2 each -> (0 + 0 + 0.2 + 0.2) / 4 = 0.1. Pearson of -MSE (centred
# .15, .05, -.05, -.15) and success (centred .15, .15, -.25, -.05): 0.05 / sqrt(0.05 * 0.11)
# = sqrt(5 / 11) = 0.6742. Top-1 regret: the offline pick a has the best success: 0.
HAND = {"a": (0.1, 0.6), "b": (0.2, 0.6), "c": (0.3, 0.2), "d": (0.4, 0.4)}


def test_closed_loop_agreement_by_hand_with_ties():
    out = rollout_agreement(cells(HAND, seeds=(0,), noise=0.0, per_task=5), "smolvla",
                            "spatial", n_resamples=200)
    assert out.success == pytest.approx([0.6, 0.6, 0.2, 0.4])
    assert out.mse == pytest.approx([0.1, 0.2, 0.3, 0.4])
    a = out.agreement
    assert a["tau_b"] == pytest.approx(3 / 30 ** 0.5)
    assert a["mmrv"] == pytest.approx(0.1)
    assert a["pearson_r"] == pytest.approx((5 / 11) ** 0.5)
    assert a["top1_regret"] == pytest.approx(0.0)
    assert set(out.intervals) == {"tau_b", "weighted_tau", "mmrv", "top1_regret", "pearson_r"}
    lo, hi = out.interval_of("mmrv")
    assert 0.0 <= lo <= hi  # MMRV is never negative, in success units
    lo, hi = out.interval_of("tau_b")
    assert lo < hi  # MSE has one fixed order here (noise 0): the width comes from the episodes


def test_the_bootstrap_draws_windows_and_episodes_each_for_all_items():
    # Window 0 puts item 0 first, window 1 item 1; success never changes: every replicate's tau
    # is +1, -1 or undefined (windows tie), so only a resampled window axis gives [-1, 1].
    ci = bootstrap_two_axes([[1.0, 0.0], [0.0, 1.0]], [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]],
                            n_resamples=100)["tau_b"]
    assert (ci.low, ci.high) == (-1.0, 1.0) and 20 < ci.undefined < 80


def test_a_tied_closed_loop_ranking_is_undefined_not_zero(tmp_path):
    from tests.factories import save_record

    recs = cells({"a": (0.10, 0.0), "b": (0.20, 0.0), "c": (0.30, 0.0)})
    out = rollout_agreement(recs, "smolvla", "spatial", n_resamples=50)
    for name in ("tau_b", "weighted_tau", "mmrv", "pearson_r"):
        value = out.agreement[name]
        assert isinstance(value, Undefined) and value != 0, name
        assert "every actual score ties (0)" in value.reason
        assert isinstance(out.intervals[name], Undefined)
    assert out.to_dict()["agreement"]["tau_b"] == {"undefined": out.agreement["tau_b"].reason}
    for r in recs:
        save_record(tmp_path / "res", r)
    text = build_report(tmp_path / "res", tmp_path / "REPORT.md", n_resamples=50,
                        plots=False).read_text()
    first_caveat = text.split("## Caveats")[1].split("\n- ")[1]
    assert ("smolvla x spatial: Kendall tau-b undefined (every actual score ties (0): no order) "
            "over 3 items") in first_caveat
    assert re.search(r"\| Kendall tau-b +\| undefined \(every actual score ties", text)


def test_pearson_r_by_hand_and_undefined_without_spread():
    assert pearson_r([1, 2, 3], [2, 4, 7]) == pytest.approx(0.99339926)  # numpy corrcoef
    assert pearson_r([1, 2, 3], [1, 1, 1]).reason == "every actual score ties (1): no order"


def test_close_items_give_a_wide_interval():
    near = rollout_agreement(cells({"a": (0.100, 0.6), "b": (0.101, 0.5), "c": (0.102, 0.4)},
                                   noise=0.05, per_task=5, scatter=0),
                             "smolvla", "spatial", n_resamples=300)
    lo, hi = near.interval_of("tau_b")
    assert lo < 0 < hi  # small N, near ties: the bootstrap must not claim agreement


def test_unpaired_init_states_are_refused():
    recs = cells({"a": (0.1, 0.9)}) + cells({"b": (0.2, 0.5)}, init_offset=100)
    out = rollout_agreement(recs, "smolvla", "spatial")
    assert out.missing and "not paired" in out.missing
    assert not out.agreement


def test_items_run_on_more_episodes_are_paired_on_the_common_ones():
    """A sequential study: b ran 10 episodes per task, a and c the first 4 of them (init states
    0-3). The agreement reads the 4 common episodes of every cell, says how many it left out,
    and gives what those cells alone give."""
    more = cells({"b": (0.2, 0.5)})
    fewer = cells({"a": (0.1, 0.9), "c": (0.3, 0.2)}, per_task=10)
    for r in fewer:  # keep each task's first 4 episodes
        r.run.rollouts["episodes"] = [e for e in r.run.rollouts["episodes"] if e["episode"] < 4]
    out = rollout_agreement(fewer + more, "smolvla", "spatial", n_resamples=200)
    assert out.missing is None and out.uncommon_episodes == 2 * 2 * 6  # b's 2 seeds x 2 tasks
    assert out.n_episodes == [16, 16, 16]  # 2 seeds x 2 tasks x 4
    assert out.success == pytest.approx([1.0, 1.0, 0.5])  # first 4 of each task: a 9, b 5, c 2
    for r in more:
        r.run.rollouts["episodes"] = [e for e in r.run.rollouts["episodes"] if e["episode"] < 4]
    alone = rollout_agreement(fewer + more, "smolvla", "spatial", n_resamples=200)
    assert alone.uncommon_episodes == 0 and alone.agreement == out.agreement
    assert alone.intervals == out.intervals


def test_candidates_are_paired_on_the_episodes_every_candidate_ran():
    """A sequential study rolled the failing item z out for 4 episodes per task, the candidates
    for 10. Over the first 4, a and b tie in success (4 of 4 each); over all 10 the success
    order is the MSE order (a 9, b 6, c 2): the candidates' agreement reads their own 10 and
    equals what a, b and c alone give, while the all-items agreement stays on the common 4."""
    good = cells({"a": (0.10, 0.9), "b": (0.20, 0.6), "c": (0.30, 0.2)})
    failing = cells({"z": (0.50, 0.0)})
    for r in failing:
        r.run.rollouts["episodes"] = [e for e in r.run.rollouts["episodes"] if e["episode"] < 4]
    out = rollout_agreement(good + failing, "smolvla", "spatial", n_resamples=200,
                            candidates=frozenset("abc"))
    alone = rollout_agreement(good, "smolvla", "spatial", n_resamples=200)
    assert (out.common_episodes, out.candidate_episodes) == (8, 20)
    assert out.candidates == ["a", "b", "c"]
    assert out.candidate_agreement == alone.agreement
    assert out.candidate_agreement["tau_b"] == pytest.approx(1.0)
    assert out.candidate_intervals == alone.intervals
    assert [m.on_candidates.value for m in out.measures] == [m.value for m in alone.measures]
    assert out.success == pytest.approx([1.0, 1.0, 0.5, 0.0])  # a, b, c, z on the common 4


def test_wilson_interval_and_labels():
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and 0.2 < hi < 0.35  # 0/10 is not "certainly 0%"
    assert wilson_interval(0, 0) == (0.0, 1.0)  # no episode: every rate is consistent
    assert record_label(make_record(kind="native")) == "native"
    assert record_label(make_record(kind="zero_image", encoder="pixels", variant="eval")) == \
        "zero_image[eval] of pixels"
    assert record_label(make_record(kind="zero_image", encoder=None, variant="eval")) == \
        "zero_image[eval] of native"
    assert closed_loop_all([make_record()]) == []  # no rollouts anywhere: no section rows


def test_report_has_the_closed_loop_table_plot_and_the_measured_caveat(tmp_path):
    from tests.factories import save_record

    for r in cells(HAND, seeds=(0,), noise=0.0, per_task=5):
        save_record(tmp_path / "res", r)
    text = build_report(tmp_path / "res", tmp_path / "REPORT.md", n_resamples=100).read_text()
    section = text.split("## Closed loop: success beside offline MSE")[1].split("\n## ")[0]
    assert re.search(r"\| a +\| 0 +\| 0.1 +\| 60.0% +\| \[0.31, 0.83\] +\| 10 ", section)
    assert re.search(r"\| MMRV +\| 0.1 +\| \[[0-9.]+, [0-9.]+\] +\| \d+ of 100 ", section)
    assert "Agreement (Kendall p over all items = " in section
    first_caveat = text.split("## Caveats")[1].split("\n- ")[1]
    # a, b, c, d are no registered encoders: no candidate among them, and that is said.
    assert re.search(r"measured \('Closed loop'\): smolvla x spatial: on the candidates no "
                     r"agreement \(0 candidate item\(s\) rolled out: fewer than 2, nothing to "
                     r"rank\); over all 4 items Kendall tau-b 0.55 \[[-0-9.]+, [-0-9.]+\], weighted tau [-0-9.]+ \[.*\], MMRV 0.1 "
                     r"\[.*\], Pearson r 0.67 \[", first_caveat), first_caveat
    assert (tmp_path / "REPORT_plots" / "closed_loop.png").exists()
