"""Closed-loop analysis on hand-made records: known rank agreement, intervals, pairing checks."""

from __future__ import annotations

import re

import numpy as np
import pytest

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
    assert same.success == pytest.approx([0.9, 0.6, 0.2])
    assert same.n_episodes == [40, 40, 40]  # 2 seeds x 2 tasks x 10 episodes
    lo, hi = same.tau_ci
    assert lo <= 1.0 <= hi + 1e-12 and lo > 0  # clearly separated items: interval above 0

    reversed_ = rollout_agreement(cells({"a": (0.10, 0.2), "b": (0.20, 0.6), "c": (0.30, 0.9)}),
                            "smolvla", "spatial", n_resamples=200)
    assert reversed_.agreement["tau_b"] == pytest.approx(-1.0)
    assert reversed_.tau_ci[1] < 0


def test_close_items_give_a_wide_interval():
    near = rollout_agreement(cells({"a": (0.100, 0.6), "b": (0.101, 0.5), "c": (0.102, 0.4)},
                             noise=0.05, per_task=5, scatter=0),
                       "smolvla", "spatial", n_resamples=300)
    lo, hi = near.tau_ci
    assert lo < 0 < hi  # small N, near ties: the bootstrap must not claim agreement


def test_unpaired_init_states_are_refused():
    recs = cells({"a": (0.1, 0.9)}) + cells({"b": (0.2, 0.5)}, init_offset=100)
    out = rollout_agreement(recs, "smolvla", "spatial")
    assert out.missing and "not paired" in out.missing
    assert not out.agreement


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


def test_report_has_the_closed_loop_table_and_plot(tmp_path):
    from tests.factories import save_record

    for r in cells({"a": (0.10, 0.9), "b": (0.20, 0.6), "c": (0.30, 0.2)}):
        save_record(tmp_path / "res", r)
    text = build_report(tmp_path / "res", tmp_path / "REPORT.md", n_resamples=100).read_text()
    section = text.split("## Closed loop: success beside offline MSE")[1].split("\n## ")[0]
    assert "Kendall tau-b 1 (p=0.333)" in section and "100 resamples" in section
    assert re.search(r"\| a +\| 0, 1 +\| 0.1 +\| 90.0% +\| \[0.77, 0.96\] +\| 40 ", section)
    assert (tmp_path / "REPORT_plots" / "closed_loop.png").exists()


def test_report_says_when_every_item_has_the_same_success(tmp_path):
    from tests.factories import save_record

    for r in cells({"a": (0.10, 0.0), "b": (0.20, 0.0)}):
        save_record(tmp_path / "res", r)
    text = build_report(tmp_path / "res", tmp_path / "REPORT.md", n_resamples=50,
                        plots=False).read_text()
    assert "Every item has the same success rate (0.0%)" in text
    assert "Rollouts in the LIBERO simulator were run for 2 rolled-out item(s)" in text
