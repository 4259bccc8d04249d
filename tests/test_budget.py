"""Known answers for the variance budget (bench.analysis.budget, hierarchy.components)."""

import numpy as np
import pytest

from bench.analysis.budget import smallest_count
from bench.analysis.hierarchy import Components, components


def test_components_recover_planted_variances():
    rng = np.random.default_rng(0)
    n_r, n_s, n_k = 150, 6, 150
    table = (rng.normal(0, 0.04, (n_r, 1, 1)) + rng.normal(0, 0.02, (n_r, n_s, 1))
             + rng.normal(0, 0.03, (1, 1, n_k)) + rng.normal(0, 0.01, (n_r, n_s, n_k)))
    c = components(table)
    assert c.release == pytest.approx(0.04 ** 2, rel=0.35)
    assert c.seed == pytest.approx(0.02 ** 2, rel=0.2)
    assert c.episode == pytest.approx(0.03 ** 2, rel=0.35)
    assert c.residual == pytest.approx(0.01 ** 2, rel=0.05)
    assert sum(c.shares().values()) == pytest.approx(1.0)


def test_one_release_puts_nothing_on_releases():
    rng = np.random.default_rng(1)
    c = components(rng.normal(0, 0.02, (1, 3, 12)))
    assert c.release == 0.0 and np.isfinite(c.df)


def test_what_it_would_take_solves_the_formula():
    # V(R) = 0.01 / R: 1.96 sqrt(0.01 / R) < 0.05 first at R = 16 (15.37 rounded up)
    by_release = Components(0.01, 0.0, 0.0, 0.0, (2, 2, 4), 1.0)
    assert smallest_count(by_release, 0.05, "releases") == 16
    assert smallest_count(by_release, 0.05, "episodes") is None  # releases' share stays
    by_episode = Components(0.0, 0.0, 0.01, 0.0, (3, 2, 4), 3.0)
    assert smallest_count(by_episode, -0.05, "episodes") == 16
    assert smallest_count(by_episode, 0.05, "seeds") is None
    # already resolved: the measured count
    assert smallest_count(by_episode, 0.5, "releases") == 3


def test_the_budget_takes_its_total_from_the_reports_interval():
    """The moments give the split, the ranking's interval the total: at the measured counts the
    pair is resolved exactly when that interval excludes 0."""
    from bench.analysis.budget import calibrated, resolves
    from bench.analysis.hierarchy import t_expansion

    parts = Components(0.0, 0.001, 0.003, 0.0, (3, 2, 12), 1e9)  # df huge: t / z = 1
    wide = calibrated(parts, (-0.01, 0.03))  # contains 0
    assert wide.mean_variance() == pytest.approx((0.02 / 1.959963984540054) ** 2)
    assert wide.shares() == pytest.approx(parts.shares())
    assert not resolves(wide, 0.01, 3, 2, 12)
    narrow = calibrated(parts, (0.005, 0.015))
    assert resolves(narrow, 0.01, 3, 2, 12)
    few = Components(0.0, 0.001, 0.003, 0.0, (3, 2, 12), 2.0)  # the t widening taken back out
    assert calibrated(few, (-0.01, 0.03)).mean_variance() == pytest.approx(
        (0.02 / t_expansion(2.0) / 1.959963984540054) ** 2)
