"""bench.screen.estimators: LogME against an explicit N x N evidence, ridge against its closed
form, k-NN and the entropy by hand, and undefined proxies with their reasons."""

from __future__ import annotations

import numpy as np
import pytest

from bench.analysis.agreement import Undefined
from bench.screen.estimators import (Moments, knn_heldout, logme, logme_fit, logme_moments,
                                     logme_windows, moments, norm_entropy, ridge_fit,
                                     ridge_heldout, ridge_windows, squared_error, token_norms)
from bench.screen.spectral import (HIGHER_ELSEWHERE, INTERIOR, NOTHING, logme_profile,
                                   spectrum)
from bench.screen.synthetic import synthetic_fit


def explicit_evidence(f: np.ndarray, y: np.ndarray, alpha: float, beta: float) -> float:
    """log N(y; 0, I/beta + F F^T / alpha) per sample, with an explicit (N, N) log-determinant."""
    n = len(y)
    cov = np.eye(n) / beta + f @ f.T / alpha
    sign, logdet = np.linalg.slogdet(cov)
    assert sign > 0
    return float(-0.5 * (n * np.log(2 * np.pi) + logdet + y @ np.linalg.solve(cov, y)) / n)


def planted(n: int, d: int, c: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(n, d))
    y = f @ rng.normal(size=(d, c)) * 0.3 + rng.normal(size=(n, c))
    return f, y


@pytest.mark.parametrize("n, d", [(200, 20), (50, 200)], ids=["N>D", "N<D"])
def test_logme_is_the_exact_maximised_evidence(n, d):
    f, y = planted(n, d)
    fits = logme_fit(f, y)
    explicit = [explicit_evidence(f, y[:, c], a, b) for c, (_, a, b) in enumerate(fits)]
    assert logme(f, y) == pytest.approx(np.mean(explicit), abs=1e-6)
    for c, (ev, a, b) in enumerate(fits):
        assert ev == pytest.approx(explicit[c], abs=1e-6)
        for da, db in ((1.05, 1), (1 / 1.05, 1), (1, 1.05), (1, 1 / 1.05)):  # a maximum (for
            # N < D it lies at beta -> infinity: the evidence there has converged to 1e-8)
            assert explicit_evidence(f, y[:, c], a * da, b * db) < ev + 1e-8


def test_logme_keeps_the_alpha_term_the_reference_fast_path_drops():
    f, y = planted(50, 200, c=1)
    ev, alpha, _ = logme_fit(f, y)[0]
    dropped = ev + (200 - 50) * np.log(alpha) / 2 / 50  # the fast path's ln|A| lacks (D-k) ln a
    assert abs(dropped - ev) > 0.1
    assert ev == pytest.approx(explicit_evidence(f, y[:, 0], *logme_fit(f, y)[0][1:]), abs=1e-6)


def test_logme_prefers_informative_features():
    f, y = planted(300, 10)
    noise = np.random.default_rng(9).normal(size=f.shape)
    assert logme(f, y) > logme(noise, y)


def test_moments_stream_in_chunks():
    f, y = planted(101, 7)
    one = moments(f, y, chunk=1000)
    many = moments(f, y, chunk=13)
    assert np.allclose(one.xtx, many.xtx) and np.allclose(one.xty, many.xty)
    assert one.n == 101 and logme_moments(one) == pytest.approx(logme_moments(many))


def standardised_closed_form(f, y, ratio):
    mu, sd = f.mean(0), f.std(0)
    z, yc = (f - mu) / sd, y - y.mean(0)
    w = np.linalg.solve(z.T @ z + ratio * len(f) * np.eye(f.shape[1]), z.T @ yc) / sd[:, None]
    return w, y.mean(0) - mu @ w


def test_ridge_equals_its_closed_form_and_scores_from_moments():
    f, y = planted(120, 6, seed=2)
    f = f * np.arange(1, 7) + 5.0  # scales and offsets the standardisation must undo
    w, b = ridge_fit(moments(f, y), 0.1)
    w_ref, b_ref = standardised_closed_form(f, y, 0.1)
    assert np.allclose(w, w_ref, atol=1e-10) and np.allclose(b, b_ref, atol=1e-10)
    test_f, test_y = planted(40, 6, seed=3)
    direct = float(((test_f @ w + b - test_y) ** 2).sum())
    assert squared_error(moments(test_f, test_y), w, b) == pytest.approx(direct, rel=1e-9)


def test_ridge_heldout_picks_a_penalty_on_training_folds_only():
    f, y = planted(200, 8, seed=4)
    folds = [moments(f[i::4], y[i::4]) for i in range(4)]
    test_f, test_y = planted(50, 8, seed=5)
    mse, ratio = ridge_heldout(folds, moments(test_f, test_y))
    w, b = standardised_closed_form(f, y, ratio)
    assert mse == pytest.approx(float(((test_f @ w + b - test_y) ** 2).mean()), rel=1e-9)


def test_constant_features_are_undefined_or_dropped():
    f, y = planted(60, 3)
    const = np.ones((60, 4))
    assert "constant" in logme_moments(moments(const, y)).reason
    assert "constant" in ridge_fit(moments(const, y), 1.0).reason
    mixed = np.concatenate([f, const], axis=1)  # constant columns add nothing
    assert logme_moments(moments(mixed, y)) == pytest.approx(logme_moments(moments(f, y)))
    folds = np.arange(60) % 3
    out, k = knn_heldout(const, y, folds, const[:5], y[:5])
    assert isinstance(out, Undefined) and k is None


def test_too_few_windows_or_folds_are_undefined():
    f, y = planted(10, 3)
    assert "too few windows" in logme_moments(moments(f[:1], y[:1])).reason
    out, _ = ridge_heldout([moments(f, y)], moments(f, y))
    assert "fold" in out.reason
    out, _ = knn_heldout(f, y, np.zeros(10, int), f, y)
    assert "fold" in out.reason
    out, _ = ridge_heldout([moments(f[:5], y[:5]), moments(f[5:], y[5:])], Moments(3, 3))
    assert "no held-out" in out.reason


def test_knn_by_hand():
    # 1-D features: two training clusters; held-out points next to each take its mean.
    train_f = np.array([[0.0], [0.1], [10.0], [10.1]])
    train_y = np.array([[1.0], [1.0], [5.0], [5.0]])
    fold = np.array([0, 1, 0, 1])
    mse, k = knn_heldout(train_f, train_y, fold, np.array([[0.05], [10.05]]),
                         np.array([[2.0], [5.0]]), chunk=1)
    assert k == 1 and mse == pytest.approx((1.0 ** 2 + 0.0) / 2)


def test_norm_entropy_by_hand():
    assert norm_entropy(np.ones((3, 4))) == pytest.approx(1.0)
    assert norm_entropy(np.array([[1.0, 0, 0, 0]])) == pytest.approx(0.0)
    two = norm_entropy(np.array([[1.0, 1.0, 0, 0]]))
    assert two == pytest.approx(np.log(2) / np.log(4))
    grid = np.zeros((2, 3, 2, 2))
    grid[:, 0] = 3.0
    grid[:, 1] = 4.0
    assert np.allclose(token_norms(grid), 5.0)
    assert "every token norm is 0" in norm_entropy(np.zeros((2, 4))).reason


@pytest.mark.parametrize("signal", [0.3, 0.0], ids=["planted", "noise"])
def test_screen_logme_is_the_evidence_orthogonal_to_the_ones_vector_when_d_exceeds_n(signal):
    # The study's real encoders screen 2,568 dims on 721 windows; centring leaves n - 1 dims, and
    # over all n the evidence had no bound there (NaN in every such screen record).
    rng = np.random.default_rng(3)
    f = rng.normal(size=(40, 120))
    y = signal * f @ rng.normal(size=(120, 3)) + rng.normal(size=(40, 3))
    z, yc = (f - f.mean(0)) / f.std(0), y - y.mean(0)
    basis = np.linalg.qr(np.eye(40) - 1 / 40)[0][:, :39]  # orthonormal, orthogonal to ones
    fq, yq = basis.T @ z, basis.T @ yc
    fits = logme_fit(fq, yq)
    explicit = [explicit_evidence(fq, yq[:, c], a, b) for c, (_, a, b) in enumerate(fits)]
    assert logme_moments(moments(f, y)) == pytest.approx(np.mean(explicit), abs=1e-6)


def test_screen_logme_prefers_informative_features_when_d_exceeds_n():
    f, y = planted(60, 150)
    noise = np.random.default_rng(9).normal(size=f.shape)
    assert logme_moments(moments(f, y)) > logme_moments(moments(noise, y))


def fixed_point(sigma: np.ndarray, z: np.ndarray, yy: np.ndarray, n: int) -> np.ndarray:
    """screen_version 2's LogME (MacKay's fixed point alpha = gamma / m^T m, beta = (n - gamma) /
    residual from alpha = beta = 1, until the evidence moves < 1e-13 per sample), kept here as
    the reference the bounded profile search must reproduce where it converges."""
    alpha, beta, last = np.ones(z.shape[1]), np.ones(z.shape[1]), None
    for _ in range(100_000):
        lam = np.clip(alpha / beta, 1e-300, 1e300)
        denom = lam[None, :] + sigma[:, None]
        mm = np.sum((z / denom) ** 2, axis=0)
        res = np.maximum(np.maximum(yy - np.sum(z ** 2 / sigma[:, None], axis=0), 0.0) + np.sum(
            (z * lam[None, :] / denom) ** 2 / sigma[:, None], axis=0), 1e-300)
        gamma = np.sum(sigma[:, None] / denom, axis=0)
        ev = (n / 2 * np.log(beta) - n / 2 * np.log(2 * np.pi) - beta / 2 * (res + lam * mm)
              - 0.5 * np.sum(np.log1p(sigma[:, None] / lam[None, :]), axis=0))
        if last is not None and np.max(np.abs(ev - last)) / n < 1e-13:
            break
        last = ev
        alpha = np.minimum(gamma / np.maximum(mm, 1e-300), 1e300)
        beta = np.minimum((n - len(sigma) + np.sum(lam / denom, axis=0)) / res, 1e300)
    return ev / n


# Tolerance of screen_version 3's LogME against 2's where 2 converged to an interior maximum
# (measured here: <= 8e-12; the tiny world and N = 721 x D = 2,568 screens: docs/PERFORMANCE.md).
LOGME_REL_TOL = 1e-9


@pytest.mark.parametrize("n, d, signal", [(200, 20, 0.3), (200, 20, 0.0), (60, 150, 0.3),
                                          (60, 150, 0.0)])
def test_the_bounded_logme_equals_the_fixed_point_where_that_converges(n, d, signal):
    rng = np.random.default_rng(n + d)
    f = rng.normal(size=(n, d))
    y = signal * f @ rng.normal(size=(d, 4)) + rng.normal(size=(n, 4))
    spec = spectrum(f, y)
    ev, _, _, where = logme_profile(spec.sigma, spec.z, spec.yy, n - 1)
    new, old = ev / (n - 1), fixed_point(spec.sigma, spec.z, spec.yy, n - 1)
    interior = np.array(where) == INTERIOR
    assert interior.any()
    assert np.allclose(new[interior], old[interior], rtol=LOGME_REL_TOL, atol=0), new - old
    # Where the supremum is a limit (lam -> 0: a noise-free fit, D > N) the fixed point crawls
    # towards it and stops early (its steps fall below 1e-13): up to ~4e-9 below it here.
    assert np.all(new >= old - 1e-12 * np.abs(old)) and np.allclose(new, old, rtol=1e-7)


def test_the_bounded_logme_equals_the_fixed_point_where_features_carry_nothing():
    """Low-rank ReLU features of a latent the targets never see (a random-init encoder's case,
    the fixed point's slowest): most columns' optimum runs off to alpha -> infinity."""
    rng = np.random.default_rng(5)
    f = np.maximum(rng.normal(size=(60, 4)) @ rng.normal(size=(4, 150)), 0.0)
    f += 1e-4 * rng.normal(size=f.shape)
    spec = spectrum(f, rng.normal(size=(60, 6)))
    ev, _, _, where = logme_profile(spec.sigma, spec.z, spec.yy, 59)
    assert NOTHING in where
    old = fixed_point(spec.sigma, spec.z, spec.yy, 59)
    assert np.allclose(ev / 59, old, rtol=LOGME_REL_TOL, atol=0), np.max(np.abs(ev / 59 - old))


def test_logme_takes_the_limit_where_the_features_explain_nothing():
    """Targets orthogonal to every feature: the evidence rises with alpha for ever; its supremum
    is the noise-only model's, -(ln(2 pi |y|^2 / n) + 1) / 2 per sample, a known answer."""
    rng = np.random.default_rng(1)
    f, y = rng.normal(size=(80, 5)), rng.normal(size=(80, 2))
    y -= f @ np.linalg.lstsq(f, y, rcond=None)[0]  # orthogonal to the features' span
    fits = logme_fit(f, y)
    yy = (y * y).sum(axis=0)
    for (ev, _, _), col in zip(fits, yy):
        assert ev == pytest.approx(-(np.log(2 * np.pi * col / 80) + 1) / 2, rel=1e-12)
    sigma, z = np.linalg.eigvalsh(f.T @ f), np.zeros((5, 2))
    assert logme_profile(sigma, z, yy, 80)[3] == [NOTHING, NOTHING]


def test_the_dual_form_equals_the_primal_one_for_logme_and_ridge():
    """D > N: the screen decomposes the N x N kernel; the Moments path decomposes D x D. Same
    LogME, same ridge penalty and held-out MSE (tolerance 1e-9 relative)."""
    fit = synthetic_fit(n=120, m=30, d=300, c=14)
    assert fit.spectrum.form == "dual"
    dual, where = logme_windows(fit.train, fit.train_targets)
    assert dual == pytest.approx(logme_moments(fit.train_total), rel=1e-9) and "interior" in where
    mse, ratio = ridge_windows(fit.train, fit.train_targets, fit.train_fold,
                               fit.heldout_features, fit.heldout_targets)
    ref_mse, ref_ratio = ridge_heldout(fit.folds, fit.heldout)
    assert ratio == ref_ratio and mse == pytest.approx(ref_mse, rel=1e-9)
    small = synthetic_fit(n=120, m=30, d=40, c=14)  # D < N: the primal form, the same answers
    assert small.spectrum.form == "primal"
    assert logme_windows(small.train, small.train_targets)[0] == pytest.approx(
        logme_moments(small.train_total), rel=1e-9)


def test_where_the_evidence_has_two_maxima_the_fixed_points_is_kept_and_flagged():
    """Two scales of eigenvalues (two large, eighteen small): the evidence peaks at lam ~ 2 and
    again higher near lam -> infinity. screen_version 2's fixed point, from lam = 1, took the
    first; so does the bounded search (the same scores), and it says a higher one exists."""
    rng = np.random.default_rng(290)
    k1, k2 = rng.integers(1, 5), rng.integers(5, 40)
    sigma = np.concatenate([10 ** rng.uniform(3, 6, k1), 10 ** rng.uniform(-1, 1, k2)])
    z = rng.normal(size=(len(sigma), 1)) * np.sqrt(sigma)[:, None] * 10 ** rng.uniform(-2, 0)
    yy = np.array([float((z[:, 0] ** 2 / sigma).sum() + rng.uniform(1, 50))])
    ev, alpha, beta, where = logme_profile(sigma, z, yy, 50)
    assert where == [INTERIOR + HIGHER_ELSEWHERE] and 0 < np.log(alpha / beta)[0] < 2
    assert ev / 50 == pytest.approx(fixed_point(sigma, z, yy, 50), rel=LOGME_REL_TOL)


@pytest.mark.parametrize("rank_space", [True, False])  # Woodbury's (r + 1) space or m x m
@pytest.mark.parametrize("d", [40, 300])  # the primal and the dual form
def test_ridge_fold_errors_through_the_hat_matrix_equal_refitting_each_fold(d, rank_space,
                                                                           monkeypatch):
    """spectral.fold_errors (one decomposition, (I - H_ff)^-1 (y_f - yhat_f)) against refitting
    ridge without each fold, directly: its columns scaled by all fitting windows' std, centred
    on its own windows (the unpenalised intercept), penalty ratio * its windows; the fold's squared
    residuals summed, at every penalty. Equal to rounding (measured 1e-13 and 4e-12; 1e-10
    asked)."""
    from bench.screen.estimators import RIDGE_GRID
    from bench.screen import spectral
    from bench.screen.spectral import fold_errors, standardiser

    fit = synthetic_fit(n=120, m=30, d=d, c=14)
    # float64 throughout, as the screen computes (the synthetic windows are float32).
    x, y, fold = fit.train.astype(float), fit.train_targets.astype(float), fit.train_fold
    keep, _, scale = standardiser(x)
    z = x[:, keep] / scale[keep]
    want = np.zeros(len(RIDGE_GRID))
    for f in np.unique(fold):
        out, into = fold != f, fold == f
        zo, yo = z[out] - z[out].mean(axis=0), y[out] - y[out].mean(axis=0)
        for i, r in enumerate(RIDGE_GRID):
            w = np.linalg.solve(zo.T @ zo + r * len(zo) * np.eye(zo.shape[1]), zo.T @ yo)
            pred = (z[into] - z[out].mean(axis=0)) @ w + y[out].mean(axis=0)
            want[i] += ((pred - y[into]) ** 2).sum()
    monkeypatch.setattr(spectral, "in_rank_space", lambda m, r, c: rank_space)
    got = fold_errors(fit.spectrum, y, fold, RIDGE_GRID)
    assert np.allclose(got, want, rtol=1e-10, atol=0), np.max(np.abs(got / want - 1))


def test_knn_folds_from_one_product_choose_what_a_product_per_fold_chooses(monkeypatch):
    """k-NN's fold distances as blocks of one N x N product (estimators.KNN_GRAM_MAX) give the
    same k and the same held-out MSE, bit for bit, as a product per fold (the path above it)."""
    from bench.screen import estimators

    fit = synthetic_fit(n=120, m=30, d=300, c=14)
    args = (fit.train, fit.train_targets, fit.train_fold, fit.heldout_features,
            fit.heldout_targets)
    shared = knn_heldout(*args, weights=fit.weights)
    monkeypatch.setattr(estimators, "KNN_GRAM_MAX", 0)
    assert knn_heldout(*args, weights=fit.weights) == shared
