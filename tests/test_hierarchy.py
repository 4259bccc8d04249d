"""Known answers for the hierarchical intervals (bench.analysis.hierarchy, rankings.paired_bootstrap):
releases, seeds within a release, held-out episodes, windows within an episode."""

import numpy as np
import pytest

from bench.analysis.hierarchy import (Units, cell_weights, levels_text, percentile,
                                      replicate_means, window_weights)
from bench.analysis.rankings import paired_bootstrap


def _units(n_tasks: int, per_task: int, windows: int) -> Units:
    episode = np.repeat(np.arange(n_tasks * per_task), windows)
    task = np.repeat(np.arange(n_tasks), per_task * windows)
    return Units(episode, task)


def _study(rng, *, gap=0.0, n_rel=5, n_seed=3, units=None, release_sd=0.0, seed_sd=0.02,
           episode_sd=0.03, window_sd=0.02) -> tuple[np.ndarray, Units]:
    """(2, R, S, W) MSEs of two encoders, encoder 1 worse by `gap`: a shared release effect and
    an encoder x release one of sd `release_sd`, seeds, episodes (shared and per encoder),
    windows."""
    units = units or _units(4, 3, 6)
    n_w = len(units.episode)
    ep = rng.normal(0, episode_sd, units.episodes.size)[units.episode]
    ep_enc = rng.normal(0, episode_sd / 2, (2, units.episodes.size))[:, units.episode]
    rel = rng.normal(0, release_sd, (1, n_rel, 1, 1)) + rng.normal(0, release_sd, (2, n_rel, 1, 1))
    seeds = rng.normal(0, seed_sd, (2, n_rel, n_seed, 1))
    windows = rng.normal(0, window_sd, (2, n_rel, n_seed, n_w))
    base = 0.1 + np.array([0.0, gap])[:, None, None, None]
    return base + rel + seeds + ep + ep_enc[:, None, None, :] + windows, units


def test_weights_draw_n_minus_one_units_and_sum_to_one():
    rng = np.random.default_rng(0)
    units = _units(4, 3, 5)
    ww = window_weights(units, 50, rng)
    assert ww.shape == (50, 60) and np.allclose(ww.sum(axis=1), 1)
    # stratified: each task keeps its share of the windows (2 of its 3 episodes drawn)
    share = np.stack([ww[:, units.task == t].sum(axis=1) for t in range(4)], axis=1)
    assert np.allclose(share, 0.25)
    cw = cell_weights(3, 2, 50, rng)
    assert np.all(cw.sum(axis=(1, 2)) == 2)  # 2 of 3 releases, 1 of 2 seeds in each


def test_one_release_one_seed_still_draws_episodes():
    """With one release and one seed the episode level still applies: with windows identical
    inside each episode, the replicates' variance is the episode mean's (s^2 / K)."""
    rng = np.random.default_rng(1)
    units = _units(6, 1, 4)  # one episode per task: drawn across tasks
    per_episode = rng.normal(0.2, 0.05, 6)
    values = np.stack([per_episode[units.episode], per_episode[units.episode] + 0.01])
    reps = replicate_means(values[:, None, None, :], units, n_resamples=20000, random_seed=0)
    expected = per_episode.std(ddof=1) / np.sqrt(6)  # n - 1 of n: unbiased (n of n: -9%)
    assert reps.draws[0].std() == pytest.approx(expected, rel=0.03)
    boot = paired_bootstrap(values[:, None, None, :], units, 0, n_resamples=500)
    assert boot.mean_hi[0] - boot.mean_lo[0] > 2 * expected  # a real width, from episodes alone
    assert boot.diff_lo[1] == pytest.approx(0.01) and boot.diff_hi[1] == pytest.approx(0.01)
    text = levels_text(1, 1, units)
    assert "1 release (not drawn" in text and "6 held-out episodes drawn across tasks" in text


def test_a_planted_release_effect_widens_the_interval():
    widths = {}
    for release_sd in (0.0, 0.08):
        values, units = _study(np.random.default_rng(3), release_sd=release_sd)
        boot = paired_bootstrap(values, units, 0, n_resamples=800, random_seed=4)
        widths[release_sd] = boot.diff_hi[1] - boot.diff_lo[1]
    assert widths[0.08] > 2 * widths[0.0]


def test_equal_encoders_are_called_tied_at_the_nominal_rate():
    """Over many planted studies of two equal encoders (every level varying), the paired
    interval contains 0 about 95% of the time (measured: 0.94 over 100); a true gap of ~4.5
    standard errors is found (called tied in 0.08)."""
    rng = np.random.default_rng(5)
    tied, found = [], []
    for _ in range(120):
        for gap, out in ((0.0, tied), (0.09, found)):
            values, units = _study(rng, gap=gap, release_sd=0.03)
            d = paired_bootstrap(values, units, 0, n_resamples=300, random_seed=int(rng.integers(1e6)))
            out.append(d.diff_lo[1] <= 0 <= d.diff_hi[1])
    assert 0.90 <= np.mean(tied) <= 1.0
    assert np.mean(found) < 0.25


def test_absent_cells_are_left_out_not_zero():
    values, units = _study(np.random.default_rng(6), n_rel=2, n_seed=2)
    values[1, 1, 1] = np.nan
    reps = replicate_means(values, units, n_resamples=200)
    assert np.isfinite(reps.point).all()
    present = np.nanmean(values[1].mean(axis=-1))
    assert reps.point[1] == pytest.approx(present)
    lo, hi = percentile(reps.draws)
    assert np.all(np.isfinite(lo)) and np.all(lo < hi)
