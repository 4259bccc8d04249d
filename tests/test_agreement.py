"""bench.analysis.agreement: hand-worked cases, ties included, and the undefined results."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats

from bench.analysis.agreement import (Undefined, agreement, as_float, bootstrap_agreement,
                                      is_defined, kendall_p_value, kendall_tau_b, mmrv,
                                      top1_regret, weighted_tau)


def test_mmrv_perfect_order_is_zero():
    assert mmrv([1, 2, 3], [10, 20, 30]) == 0.0


def test_mmrv_reversed_order_by_hand():
    # i=0: violated by j=1 (|3-2|) and j=2 (|3-1|) -> 2; i=1: j=0 and j=2 -> 1; i=2: j=0 -> 2.
    assert mmrv([1, 2, 3], [3, 2, 1]) == pytest.approx(5 / 3)


def test_mmrv_predicted_ties_are_violations_when_actual_separates():
    # S all tie: i=0 (worst actual) violates nothing; i=1 is violated by j=0 (1); i=2 by j=0 (2).
    assert mmrv([1, 1, 1], [1, 2, 3]) == pytest.approx((0 + 1 + 2) / 3)


def test_mmrv_actual_ties_cost_nothing():
    # the only disagreeing pair (1, 0) has |R_1 - R_0| = 0.
    assert mmrv([1, 2, 3], [1, 1, 2]) == 0.0


def test_mmrv_is_in_units_of_actual_and_matches_simplerenv_loop():
    rng = np.random.default_rng(3)
    s, r = rng.normal(size=7), rng.normal(size=7)
    loop = np.mean([max(abs(r[i] - r[j]) if (s[i] > s[j]) != (r[i] > r[j]) else 0.0
                        for j in range(7)) for i in range(7)])
    assert mmrv(s, r) == pytest.approx(loop)
    assert mmrv(s, 10 * r) == pytest.approx(10 * loop)


def test_mmrv_undefined_when_every_actual_ties():
    out = mmrv([1, 2, 3], [0.5, 0.5, 0.5])
    assert isinstance(out, Undefined) and "every actual score ties" in out.reason


def test_tau_b_with_a_tie_by_hand():
    # 6 pairs, 5 concordant, 0 discordant, one pair tied in actual: 5 / sqrt(6 * 5).
    assert kendall_tau_b([1, 2, 3, 4], [1, 2, 2, 3]) == pytest.approx(5 / math.sqrt(30))
    assert kendall_tau_b([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)


@pytest.mark.parametrize("predicted, actual, side", [
    ([2, 2, 2], [1, 2, 3], "predicted"), ([1, 2, 3], [7, 7, 7], "actual")])
def test_tau_of_a_tied_ranking_is_undefined_not_zero(predicted, actual, side):
    for stat in (kendall_tau_b, weighted_tau, kendall_p_value):
        out = stat(predicted, actual)
        assert isinstance(out, Undefined) and f"every {side} score ties" in out.reason
        assert not is_defined(out) and math.isnan(as_float(out))


def test_too_few_items_and_non_finite_are_undefined_with_reason():
    assert "fewer than 2" in kendall_tau_b([1.0], [2.0]).reason
    assert "fewer than 2" in top1_regret([], []).reason
    assert "not finite" in mmrv([1, float("nan")], [1, 2]).reason
    with pytest.raises(ValueError, match="one length"):
        mmrv([1, 2], [1, 2, 3])


def test_weighted_tau_is_scipys_and_weighs_the_top():
    base = [4, 3, 2, 1]
    swap_top, swap_bottom = [3, 4, 2, 1], [4, 3, 1, 2]
    assert weighted_tau(base, base) == pytest.approx(1.0)
    assert weighted_tau(swap_top, base) < weighted_tau(swap_bottom, base)
    assert weighted_tau(swap_top, base) == pytest.approx(
        scipy.stats.weightedtau(swap_top, base).statistic)


def test_top1_regret_by_hand_and_tied_picks_take_the_worst():
    assert top1_regret([1, 3, 2], [0.1, 0.9, 1.0]) == pytest.approx(0.1)
    assert top1_regret([3, 3, 1], [0.5, 0.9, 1.0]) == pytest.approx(0.5)
    assert top1_regret([1, 2, 3], [1, 2, 3]) == 0.0
    assert isinstance(top1_regret([5, 5], [1, 2]), Undefined)


def test_regret_on_mse_is_pick_minus_best():
    mse_cheap, mse_graft = np.array([0.2, 0.1, 0.3]), np.array([0.05, 0.07, 0.04])
    assert top1_regret(-mse_cheap, -mse_graft) == pytest.approx(0.07 - 0.04)


def test_agreement_bundles_and_serialises_undefined():
    a = agreement([1, 2, 3], [5, 5, 5])
    d = a.to_dict()
    assert d["n"] == 3 and d["top1_regret"] == 0.0
    assert set(d["tau_b"]) == {"undefined"} and "actual" in d["mmrv"]["undefined"]


def test_bootstrap_interval_is_paired_over_windows():
    rng = np.random.default_rng(0)
    base = -np.array([[0.1], [0.2], [0.3], [0.4]]) - 0.001 * rng.random((4, 50))
    out = bootstrap_agreement([4, 3, 2, 1], base, n_resamples=200)
    assert out["tau_b"].low == pytest.approx(1.0) and out["tau_b"].high == pytest.approx(1.0)
    assert out["mmrv"].high == 0.0 and out["tau_b"].undefined == 0
    close = -np.array([[0.1], [0.1], [0.5], [0.6]]) - rng.normal(0, 0.05, (4, 50))
    wide = bootstrap_agreement([4, 3, 2, 1], close, n_resamples=200)["tau_b"]
    assert wide.low < 1.0 and wide.high == pytest.approx(1.0)


def test_bootstrap_of_a_tied_prediction_is_undefined_with_reason():
    out = bootstrap_agreement([1, 1, 1], np.zeros((3, 5)) + [[1], [2], [3]], n_resamples=20)
    assert isinstance(out["tau_b"], Undefined) and "every predicted score ties" in out["tau_b"].reason
    assert out["mmrv"].low == out["mmrv"].high == pytest.approx(1.0)  # (0 + 1 + 2) / 3
    with pytest.raises(ValueError, match=r"\(n, W\)"):
        bootstrap_agreement([1, 2], np.zeros(2))


def _seed_case(errors_by_seed, success_by_seed, windows=6, episodes=6):
    """SeedStacks whose windows and episodes carry no variance: every spread is the seeds'."""
    from bench.analysis.two_axes import SeedStacks

    pred = -np.repeat(np.asarray(errors_by_seed, float)[:, :, None], windows, axis=2)
    act = np.repeat(np.asarray(success_by_seed, float)[:, :, None], episodes, axis=2)
    n, s = pred.shape[:2]
    return pred.mean(axis=1), act.mean(axis=1), SeedStacks(pred, act, np.full(n, s), np.arange(n))


def test_a_bootstrap_over_seeds_widens_what_the_seeds_disagree_on():
    """Planted: the middle item's seed 0 is the best offline and the worst in closed loop, its
    seed 1 the reverse; over the means the orders agree (tau 1), over windows and episodes alone
    the interval is [1, 1]; drawing seeds as well must reach below it."""
    from bench.analysis.two_axes import bootstrap_two_axes

    pred, act, seeds = _seed_case([[0.1, 0.1], [0.05, 0.35], [0.3, 0.3]],
                                  [[0.9, 0.9], [0.1, 0.95], [0.2, 0.2]])
    alone = bootstrap_two_axes(pred, act, n_resamples=200, statistics=("tau_b",))
    drawn = bootstrap_two_axes(pred, act, n_resamples=200, statistics=("tau_b",), seeds=seeds)
    assert (alone["tau_b"].low, alone["tau_b"].high) == (1.0, 1.0)
    assert drawn["tau_b"].low < 0 and drawn["tau_b"].high == 1.0


def test_one_seed_per_item_gives_the_two_axis_intervals_exactly():
    from bench.analysis.two_axes import SeedStacks, bootstrap_two_axes

    rng = np.random.default_rng(3)
    pred, act = rng.normal(size=(4, 1, 9)), rng.random((4, 1, 7))
    seeds = SeedStacks(pred, act, np.ones(4, int), np.arange(4))
    alone = bootstrap_two_axes(pred[:, 0], act[:, 0], n_resamples=100)
    drawn = bootstrap_two_axes(pred[:, 0], act[:, 0], n_resamples=100, seeds=seeds)
    assert {k: (v.low, v.high) for k, v in alone.items()} == {
        k: (v.low, v.high) for k, v in drawn.items()}


def test_the_two_axis_draw_takes_episodes_as_the_unit_when_given_units():
    """Planted: every held-out episode's windows are one value, so copying each window three
    times within its episode adds no information. Drawn by episodes (units), the interval is
    the same as before the copies (the same draws of 4 episodes); drawn window by window, it
    narrows as if there were 3x the data."""
    from bench.analysis.two_axes import bootstrap_two_axes
    from bench.analysis.hierarchy import Units

    rng = np.random.default_rng(5)
    # 5 items x 12 held-out episodes (2 tasks), one window each; 8 rollout episodes, no spread
    pred = rng.normal(size=(5, 12)) + 0.3 * np.arange(5)[:, None]
    act = np.repeat(rng.random((5, 1)), 8, axis=1)
    tripled, tasks = np.repeat(pred, 3, axis=1), np.repeat([0, 1], 6)
    episodes = (Units(np.arange(12), tasks), Units(np.arange(8), np.repeat([0, 1], 4)))
    copies = (Units(np.repeat(np.arange(12), 3), np.repeat(tasks, 3)), episodes[1])

    def width(p, units=None):
        ci = bootstrap_two_axes(p, act, n_resamples=400, statistics=("pearson_r",),
                                units=units)["pearson_r"]
        return ci.high - ci.low

    assert width(tripled, copies) == pytest.approx(width(pred, episodes), rel=0.15)
    assert width(tripled) < 0.8 * width(pred)
