"""The verdict within the working group on hand-made records: a planted order among working
items comes back resolved, planted equal items stay open with the McNemar size worked by hand,
and the working rule leaves out what does not beat the failing reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.analysis.working_group import mcnemar_episodes, working_group
from tests.factories import make_record

TASKS, PER_TASK = 4, 10


def episodes(successes) -> dict:
    """A record's rollouts from a (TASKS * n,) 0/1 list, task-major (episode e of task t)."""
    n = len(successes) // TASKS
    return {"episodes": [{"task": t, "episode": e, "init_state": 49 - e,
                          "success": bool(successes[t * n + e]), "steps": 50}
                         for t in range(TASKS) for e in range(n)],
            "success_rate": float(np.mean(successes))}


def scattered(rate: float, seed: int, per_task: int = PER_TASK) -> list[int]:
    """round(rate * per_task) successes in each task, on episodes drawn at random."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(TASKS):
        row = np.zeros(per_task, int)
        row[rng.permutation(per_task)[:round(rate * per_task)]] = 1
        out += row.tolist()
    return out


def graft(encoder: str, mse: float, successes, seed: int = 0):
    return make_record(encoder=encoder, seed=seed, level=mse, rollouts=episodes(successes))


CANDIDATES = frozenset({"a", "b", "c", "e", "x", "y", "native"})


def test_a_planted_order_among_working_items_is_recovered():
    records = [graft("a", 0.10, scattered(0.9, 1, 20)), graft("b", 0.11, scattered(0.5, 2, 20)),
               graft("c", 0.12, scattered(0.15, 3, 20)),  # 3 successes of 20 a task: works
               graft("e", 0.13, scattered(0.0, 4, 20)),  # a candidate that never succeeds
               graft("blind", 0.50, scattered(0.0, 5, 20))]
    wg = working_group(records, "smolvla", "spatial", CANDIDATES, n_resamples=300)
    assert wg.missing is None and wg.reference == "blind"
    assert [s.item for s in wg.items] == ["a", "b", "c", "blind", "e"]  # ties by name
    assert wg.order == ["a", "b", "c"]  # e and blind do not beat blind's 0 successes
    a_b = wg.pairs[0]
    assert (a_b.upper, a_b.lower, a_b.paired_episodes) == ("a", "b", 80)
    assert a_b.resolved and a_b.mse_agrees and a_b.more is None
    assert a_b.diff == pytest.approx(0.9 - 0.5)
    assert all(p.resolved and p.mse_agrees for p in wg.pairs)
    assert wg.tau_b == pytest.approx(1.0)  # MSE a < b < c: the same order, in every replicate
    assert (wg.tau_b_ci.low, wg.tau_b_ci.high) == (1.0, 1.0)


# Hand-worked: x and y succeed equally often per task in truth; on the 40 paired episodes x
# alone succeeds on 6, y alone on 4. p_d = 10 / 40 = 0.25, d = 2 / 40 = 0.05; Connor's size:
# (1.959964 * 0.5 + 0.841621 * sqrt(0.25 - 0.0025))^2 / 0.0025
#   = (0.979982 + 0.418700)^2 / 0.0025 = 1.398682^2 / 0.0025 = 782.52 -> 783, i.e. 743 more.
def test_planted_equal_items_stay_open_with_mcnemars_size_by_hand():
    both = [1] * 20 + [0] * 10  # 30 episodes with the same outcome for x and y
    x = both + [1] * 6 + [0] * 4
    y = both + [0] * 6 + [1] * 4
    order = np.random.default_rng(0).permutation(40)  # spread over the 4 tasks
    x, y = np.asarray(x)[order], np.asarray(y)[order]
    records = [graft("x", 0.10, x), graft("y", 0.11, y), graft("blind", 0.5, [0] * 40)]
    wg = working_group(records, "smolvla", "spatial", CANDIDATES, n_resamples=300)
    assert wg.order == ["x", "y"]
    (pair,) = wg.pairs
    assert not pair.resolved and pair.ci[0] < 0 < pair.ci[1]
    assert (pair.upper_only, pair.lower_only) == (6 / 40, 4 / 40)
    assert pair.needed == pytest.approx(782.52, abs=0.01)
    assert pair.more == 783 - 40
    assert wg.open_pairs == [pair]


def test_no_size_resolves_an_observed_tie():
    assert mcnemar_episodes(0.1, 0.1) == math.inf
    # equal shares that are means over three cells, unequal in their last bits: no size either
    a = np.array([2, 0, 1, 3, 0, 3, 2, 1, 3, 3, 1, 2]) / 3  # successes of 3 cells, 12 episodes
    b = np.array([3, 2, 1, 3, 3, 0, 2, 3, 0, 1, 2, 1]) / 3
    upper, lower = float(np.mean(a * (1 - b))), float(np.mean((1 - a) * b))
    assert upper != lower and mcnemar_episodes(upper, lower) == math.inf
    assert mcnemar_episodes(0.15, 0.10) == pytest.approx(782.52, abs=0.01)


def test_items_on_different_episodes_are_compared_on_the_ones_both_ran():
    """A sequential study runs some items more rounds: an item's success is over its own
    episodes, a neighbour difference over the common ones, and two seeds are two cells."""
    # a: 80 episodes, 5 of the first 10 of each task (the common ones) and all later 10 succeed
    long = ([1, 0] * 5 + [1] * 10) * TASKS
    short = scattered(0.4, 8, 10)
    records = [graft("a", 0.10, long), graft("a", 0.10, long, seed=1),
               graft("b", 0.20, short), make_record(kind="native", encoder=None, level=0.3,
                                                    rollouts=episodes([0] * 40))]
    wg = working_group(records, "smolvla", "spatial", frozenset({"a", "b"}), n_resamples=200)
    assert wg.reference is None  # no non-candidate graft: the reference is success 0
    a = next(s for s in wg.items if s.item == "a")
    assert (a.cells, a.episodes, a.success) == (2, 160, pytest.approx(0.75))
    (pair,) = wg.pairs
    assert pair.paired_episodes == 40 and pair.diff == pytest.approx(0.5 - 0.4)
    assert "native" not in wg.order  # not a candidate here: never in the working group


def test_the_report_gives_the_verdict_and_the_open_pairs(tmp_path):
    """REPORT.md's section: the native policy and two Lites work against Lite0's random twin
    (the reference); the Lites' pair stays open with its McNemar size."""
    from types import SimpleNamespace

    from bench.report.working_group import working_group_section

    both = [1] * 20 + [0] * 10
    lite0 = both + [1] * 6 + [0] * 4
    lite1 = both + [0] * 6 + [1] * 4
    records = [graft("effnet_lite0", 0.11, lite0), graft("effnet_lite1", 0.10, lite1),
               graft("effnet_lite0_random", 0.3, [1] * 4 + [0] * 36),
               make_record(kind="native", encoder=None, level=0.2, rollouts=episodes([1] * 40))]
    wg = working_group(records, "smolvla", "spatial",
                       frozenset({"native", "effnet_lite0", "effnet_lite1"}), n_resamples=100)
    ctx = SimpleNamespace(working_groups=[wg], results=SimpleNamespace(root=tmp_path))
    section = " ".join(working_group_section(ctx).split())  # tables' padding collapsed
    assert "**smolvla x spatial** (reference: effnet_lite0_random)" in section
    assert ("Closed-loop order of the 3 working item(s) ('>' resolved, '~' open): native > "
            "effnet_lite0 ~ effnet_lite1.") in section
    assert "| effnet_lite0 - effnet_lite1 | 40 | 15.0% / 10.0% | +5.0 pts" in section
    assert "743 (783 in all)" in section
    assert "offline MSE orders 0 of the 1 resolved neighbour pair(s) the same way" in section


def test_the_section_names_the_sequential_design_the_folder_was_run_under(tmp_path):
    import json
    from types import SimpleNamespace

    from bench.analysis.sequential_study import DESIGN_FILE
    from bench.report.working_group import design_line

    ctx = SimpleNamespace(results=SimpleNamespace(root=tmp_path))
    assert design_line(ctx) is None
    (tmp_path / DESIGN_FILE).write_text(json.dumps({
        "design": {"rule": "racing v1", "alpha": 0.05, "budget": 1500, "units_per_round": 36},
        "last": {"rounds": 4, "stop": "resolved", "spent_episodes": 700}}))
    assert design_line(ctx) == (
        "Run as a sequential study (sequential.json: racing v1, alpha 0.05, budget 1500 "
        "episodes, 36 episodes per item a round): 4 round(s), stopped: resolved; 700 episodes "
        "rolled out in all.")
    pairs = [{"upper": "a", "lower": "b", "declared": 1}, {"upper": "b", "lower": "c", "declared": 0}]
    (tmp_path / DESIGN_FILE).write_text(json.dumps({
        "design": {"rule": "racing v1", "alpha": 0.05, "budget": 1500, "units_per_round": 36},
        "last": {"rounds": 1, "stop": None, "spent_episodes": 108, "order": ["a", "b", "c"],
                 "pairs": pairs}}))
    assert design_line(ctx).endswith("1 round(s), stopped: not yet; 108 episodes rolled out in "
                                     "all. Its order ('>' declared, '~' open; ties in success "
                                     "keep the --items order): a > b ~ c.")
