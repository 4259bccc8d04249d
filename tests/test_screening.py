"""bench.screen.estimators: LogME against an explicit N x N evidence, ridge against its closed
form, k-NN and the entropy by hand, and undefined proxies with their reasons."""

from __future__ import annotations

import numpy as np
import pytest

from bench.analysis.agreement import Undefined
from bench.screen.estimators import (Moments, knn_heldout, logme, logme_fit, logme_moments,
                                     moments, norm_entropy, ridge_fit, ridge_heldout,
                                     squared_error, token_norms)


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
