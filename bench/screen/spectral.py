"""The supervised proxies' one decomposition: the training-standardised windows Z (n, d) by the
eigendecomposition of the cheaper of Z^T Z (d x d, primal) and Z Z^T (n x n, dual), and LogME's
evidence maximised on it in bounded work.

Why: the study's real encoders screen d ~ 2,576 columns on n ~ 721 windows; a d x d eigh there
costs ~2.3 s on one thread against ~0.05 s for the n x n one, and the ridge folds took one each.
Both forms give the same nonzero eigenvalues sigma = s^2 of Z = U S V^T and the same
z = V^T Z^T Yc = S U^T Yc, which is all LogME reads; ridge's prediction for new windows Q is
Q V (sigma + lambda)^-1 z, with Q V computed as Q Z^T U / s in the dual form.

LogME (bench.screen.estimators) maximises the evidence over (alpha, beta); for a fixed
lam = alpha / beta the best beta is closed-form (n / E(lam), E the penalised residual), which
leaves one variable per target column: `logme_profile` scans ln(lam) on a fixed grid spanning the
spectrum, climbs from lam = 1 (where the fixed point started) to the first maximum, then
narrows that grid interval by golden section (GOLDEN_STEPS steps). The
MacKay fixed point it replaces needed up to 100,000 iterations (minutes) where the features carry
nothing and the optimum runs off to lam -> infinity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from bench.stats import Undefined

CONSTANT_REL_VAR = 1e-10  # a column whose variance is below this fraction of its mean square
ZERO_EIGEN_REL = 1e-12  # eigenvalues below this fraction of the largest are rounded zeros
GRID_STEP = 0.25  # ln(lam) between grid points
GRID_BELOW, GRID_ABOVE = 40.0, 30.0  # ln(lam) margins below the smallest / above the largest sigma
GOLDEN = (np.sqrt(5.0) - 1) / 2
# The best grid interval (width 0.5) shrinks to 0.5 x 0.618^40 ~ 2e-9 in ln(lam), where the
# evidence per sample is within ~1e-17 of its maximum (it is quadratic there).
GOLDEN_STEPS = 40
INTERIOR, NOISE_FREE, NOTHING = "interior", "lam->0", "lam->inf"
HIGHER_ELSEWHERE = " (higher elsewhere)"  # the evidence has a higher maximum at another lam


@dataclass
class Spectrum:
    """Z = the standardised kept columns of n fitting windows, Yc their centred targets:
    sigma (r,) the nonzero eigenvalues of Z^T Z, z (r, C) = V^T Z^T Yc, yy (C,) = column sums of
    Yc^2, `ymean` (C,); `project(x)` -> (m, r) new windows x (m, D) standardised and put on V;
    `form`: "primal" or "dual", which matrix was decomposed. The dual form also keeps Z itself
    (`windows`, which its `project` reads anyway), `standard(x)` -> new windows x (m, D)
    standardised (m, d), `gram` Z Z^T (n, n) and `keep` (D,) the kept columns: k-NN reads them
    (knn_windows). The primal form keeps none: there Z would outlive the decomposition."""

    n: int
    sigma: np.ndarray
    z: np.ndarray
    yy: np.ndarray
    ymean: np.ndarray
    project: Callable[[np.ndarray], np.ndarray]
    form: str
    windows: np.ndarray | None = None
    standard: Callable[[np.ndarray], np.ndarray] | None = None
    gram: np.ndarray | None = None
    keep: np.ndarray | None = None
    basis: np.ndarray | None = None  # P = Z V (n, r): the fitting windows on V (fold_errors)

    def predict(self, basis: np.ndarray, ratio: float) -> np.ndarray:
        """Ridge's predictions (m, C) at penalty ratio * n for windows already projected."""
        return basis @ (self.z / (self.sigma + ratio * self.n)[:, None]) + self.ymean


def standardiser(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | Undefined:
    """(keep (D,) bool, mean (D,), scale (D,)) of windows x (n, D) by their own mean and std:
    a column whose variance is at most CONSTANT_REL_VAR of its mean square carries nothing."""
    parts = standard_parts(x)
    return parts if isinstance(parts, Undefined) else parts[:3]


def standard_parts(x: np.ndarray):
    """standardiser's (keep, mean, scale) and the centred windows x - mean (n, D) float64 it
    computed them from: spectrum scales that array instead of converting and centring x again
    (the same operations on the same numbers, so the same bits)."""
    x = np.asarray(x, float)
    n = len(x)
    if n < 2:
        return Undefined(f"{n} fitting window(s): too few windows")
    mean = x.mean(axis=0)
    centred = x - mean
    var = (centred ** 2).mean(axis=0)
    # The mean square as var + mean^2: one pass less than (x * x).mean(), and it only decides
    # `keep`, at a threshold no real column sits within rounding of.
    keep = var > CONSTANT_REL_VAR * np.maximum(var + mean * mean, 1e-300)
    if not keep.any():
        return Undefined(f"all {x.shape[1]} feature columns constant over the {n} fitting windows")
    return keep, mean, np.where(keep, np.sqrt(np.where(keep, var, 1.0)), 1.0), centred


def spectrum(x: np.ndarray, y: np.ndarray, eigh: Callable = np.linalg.eigh
             ) -> Spectrum | Undefined:
    """The Spectrum of windows x (n, D) with targets y (n, C), in the cheaper form; `eigh`
    decomposes the symmetric Gram ((sigma, vectors), as numpy's)."""
    stats = standard_parts(x)
    if isinstance(stats, Undefined):
        return stats
    keep, mean, scale, centred = stats
    mean, scale = mean[keep], scale[keep]

    def standard(q: np.ndarray) -> np.ndarray:
        return (np.asarray(q, float)[:, keep] - mean) / scale

    # In place (centred is ours): the same bits and memory order, one (n, D) array less.
    zs = centred if keep.all() else centred[:, keep]
    zs /= scale
    y = np.asarray(y, float)
    ymean = y.mean(axis=0)
    yc = y - ymean
    n, d = zs.shape
    if d <= n:
        sigma, vecs = eigh(zs.T @ zs)
        rank = sigma > ZERO_EIGEN_REL * max(sigma.max(), 0.0)
        sigma, vecs = sigma[rank], vecs[:, rank]
        z = vecs.T @ (zs.T @ yc)
        return Spectrum(n, sigma, z, (yc * yc).sum(axis=0), ymean,
                        lambda q: standard(q) @ vecs, "primal", basis=zs @ vecs)
    gram = zs @ zs.T
    sigma, vecs = eigh(gram)
    rank = sigma > ZERO_EIGEN_REL * max(sigma.max(), 0.0)
    sigma, vecs = sigma[rank], vecs[:, rank]
    s = np.sqrt(sigma)
    z = s[:, None] * (vecs.T @ yc)
    to_v = vecs / s  # Q V = Q Z^T U S^-1
    return Spectrum(n, sigma, z, (yc * yc).sum(axis=0), ymean,
                    lambda q: (standard(q) @ zs.T) @ to_v, "dual", zs, standard, gram, keep,
                    basis=vecs * s)  # Z V = U S


def knn_windows(features: np.ndarray, weights: np.ndarray | None = None,
                spec: Spectrum | Undefined | None = None):
    """k-NN's (f(x) -> standardised kept columns (times `weights` (D,) when given), f(features),
    f(features) f(features)^T or None), by `features`' own mean and std; or Undefined. From
    `spec`, the same windows' Spectrum, where given (weighted_windows). Else f(features) is
    scaled in place on the centred copy the statistics were computed on (the same numbers and
    memory order as calling f)."""
    if isinstance(spec, Spectrum) and spec.windows is not None:
        return weighted_windows(spec, weights)
    stats = standard_parts(features)
    if isinstance(stats, Undefined):
        return stats
    keep, mean, scale, centred = stats
    factor = (np.ones(len(keep)) if weights is None else np.asarray(weights, float))[keep]
    own = centred if keep.all() else centred[:, keep]
    own /= scale[keep]
    own *= factor
    return lambda x: (np.asarray(x, float)[:, keep] - mean[keep]) / scale[keep] * factor, own, None


def weighted_windows(spec: Spectrum, weights: np.ndarray | None):
    """knn_windows from `spec`: Z (spec.windows) is what knn_windows' own path scales by the
    weights, so the same bits; and in the dual form the N x N product comes from spec.gram, not
    another N x N x D one: most columns share one weight w (the cameras'), so it is w^2 Z Z^T
    plus the few others' (the state's) correction. Other rounding than a product of its own:
    k-NN only compares these fold distances, to choose k (its held-out ones are z's own)."""
    factor = (np.ones(len(spec.keep)) if weights is None else np.asarray(weights, float))[spec.keep]
    z = spec.windows * factor
    gram = None
    if spec.gram is not None:
        values, counts = np.unique(factor, return_counts=True)
        common = values[np.argmax(counts)]
        gram = common * common * spec.gram
        other = factor != common
        if other.any():
            zo = spec.windows[:, other]
            gram += (zo * (factor[other] ** 2 - common * common)) @ zo.T
    return (lambda x: spec.standard(x) * factor), z, gram


def fold_errors(spec: Spectrum, y: np.ndarray, fold: np.ndarray, ratios) -> np.ndarray:
    """(len(ratios),) ridge's squared error summed over the episode folds of the fitting windows
    (`fold` (n,)), each fold predicted by a fit on the others penalised ratio * their count (the
    same penalty per window as the final fit), at each penalty ratio: grouped cross-validation
    through the hat matrix of a fit on ALL of them at that penalty (`spec`, targets y (n, C)),
    exactly: with H = 11^T / n + P diag(a) P^T (P = Z V, a = 1 / (sigma + lambda): the
    unpenalised intercept and the penalised columns), a fold's residuals under the fit without it
    are (I - H_ff)^-1 (y_f - yhat_f) (Sherman-Morrison-Woodbury). So the fold fits share the
    fitting windows' scales (the intercept centres each fold fit on its own windows) and no fold
    is decomposed again: one small Cholesky per fold and penalty (screen_version 4; until 3 each
    fold was also scaled by its own windows and decomposed: five eighs)."""
    yc = np.asarray(y, float) - spec.ymean
    rows = [np.flatnonzero(fold == f) for f in np.unique(fold)]
    parts = [spec.basis[r] for r in rows]
    errors = np.zeros(len(ratios))
    for i, ratio in enumerate(ratios):
        for r, part in zip(rows, parts):
            # The fit without the fold penalised ratio * its own windows, as the final fit is
            # on all of them: the same penalty per window. Its residuals come from the fit on
            # all windows at that same penalty.
            a = 1.0 / (spec.sigma + ratio * (spec.n - len(r)))
            residual = yc[r] - part @ (a[:, None] * spec.z)
            errors[i] += _held_out_sq(part, a, spec.n, residual)
    return errors


def in_rank_space(m: int, r: int, c: int) -> bool:
    """Whether a fold of m windows is cheaper through the r + 1 columns of H_ff's factor
    (Woodbury) than through H_ff itself: flops of each (r small: the primal form's few columns)."""
    return m * r * r + 2 * m * r * c + r ** 3 + r * r * c < m * m * r + 2 * m ** 3 + m * m * c


def _held_out_sq(part: np.ndarray, a: np.ndarray, n: int, rf: np.ndarray) -> float:
    """|(I - H_ff)^-1 rf|^2 for H_ff = B B^T, B = [part diag(sqrt a), 1 / sqrt n] (m, r + 1):
    in the m x m space, <M^2, rf rf^T> with M = (I - H_ff)^-1 (an m x m inverse instead of a
    solve with every target column, C ~ 350 here); or, where cheaper, in the (r + 1) space
    (Woodbury: M rf = rf + B (I - B^T B)^-1 B^T rf). Both SPD (a fold never holds every
    window): Cholesky."""
    m, r = part.shape
    if in_rank_space(m, r, rf.shape[1]):
        b = np.hstack([part * np.sqrt(a), np.full((m, 1), 1.0 / np.sqrt(n))])
        inner = np.eye(r + 1) - b.T @ b
        e = rf + b @ cho_solve(cho_factor(inner, overwrite_a=True, check_finite=False),
                               b.T @ rf, check_finite=False)
        return float(np.einsum("ij,ij->", e, e))
    inside = np.eye(m) - (part * a) @ part.T - 1.0 / n
    inverse = cho_solve(cho_factor(inside, overwrite_a=True, check_finite=False), np.eye(m),
                        check_finite=False)
    return float(np.einsum("ij,ij->", inverse @ inverse, rf @ rf.T))


def _profile(lam: np.ndarray, sigma: np.ndarray, w: np.ndarray, unfit: np.ndarray, n: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """(log evidence at beta's optimum, E) at lam (C,) per column: E = unfit + sum w lam/(lam+s),
    the residual plus lam m^T m; ln|A| / 2 - d/2 ln(alpha) as one sum of log1p (no two large
    terms cancel where lam is large)."""
    ratio = sigma[:, None] / lam[None, :]  # (r, C)
    # In place, two (r, C) arrays instead of four: golden-section calls this 42 times per fit.
    share = np.add(1.0, ratio)
    e = np.maximum(unfit + np.divide(w, share, out=share).sum(axis=0), 1e-300)
    return (n / 2 * np.log(n / e) - n / 2 * (np.log(2 * np.pi) + 1)
            - 0.5 * np.log1p(ratio, out=ratio).sum(axis=0)), e


def logme_profile(sigma: np.ndarray, z: np.ndarray, yy: np.ndarray, n: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(log evidence (C,), alpha (C,), beta (C,), where each optimum lies) at the maximum over
    lam that each column climbs to from lam = 1 (`_ascend`), beta = n / E(lam), from the
    nonzero eigenvalues `sigma` (r,) of F^T F and z = V^T F^T Y (r, C), yy (C,) = |y|^2, `n`
    the dimension the targets live in. Where lies:
    INTERIOR (a maximum inside the grid), NOISE_FREE (at its lowest lam: the features fit the
    targets, beta -> infinity) or NOTHING (at its highest, the limit alpha -> infinity taken:
    the features explain nothing), each + HIGHER_ELSEWHERE where the grid saw a higher maximum
    (kept, not taken: the same scores as screen_version 2). Bounded: one grid, then
    GOLDEN_STEPS steps."""
    w = z ** 2 / sigma[:, None]
    unfit = np.maximum(yy - w.sum(axis=0), 0.0)  # least squares' residual (lam -> 0)
    low, high = np.log(sigma.min()) - GRID_BELOW, np.log(sigma.max()) + GRID_ABOVE
    grid = np.arange(low, high + GRID_STEP, GRID_STEP)
    lam = np.exp(grid)
    # (G, C) at once: E = unfit + Q w with Q (G, r) = lam / (lam + sigma), one matrix product.
    ratio = sigma[None, :] / lam[:, None]
    e = np.maximum(unfit[None, :] + (1.0 / (1.0 + ratio)) @ w, 1e-300)
    logdet = 0.5 * np.sum(np.log1p(ratio), axis=1)
    values = n / 2 * np.log(n / e) - n / 2 * (np.log(2 * np.pi) + 1) - logdet[:, None]
    best = _ascend(values, int(np.clip(np.searchsorted(grid, 0.0), 0, len(grid) - 1)))
    cols = np.arange(len(best))
    higher = values.max(axis=0) > values[best, cols] + 1e-12 * np.abs(values[best, cols])
    t, ev, e_t = _golden(grid[np.maximum(best - 1, 0)], grid[np.minimum(best + 1, len(grid) - 1)],
                         sigma, w, unfit, n)
    better = ev > values[best, cols]  # never below the grid's best (a flat top may not move)
    t, ev, e_t = (np.where(better, t, grid[best]), np.where(better, ev, values[best, cols]),
                  np.where(better, e_t, e[best, cols]))
    where = [(NOISE_FREE if i == 0 else NOTHING if i == len(grid) - 1 else INTERIOR)
             + (HIGHER_ELSEWHERE if h else "") for i, h in zip(best, higher)]
    # At the grid's top the evidence still rises to its limit lam -> infinity (E -> |y|^2).
    limit = n / 2 * np.log(n / np.maximum(yy, 1e-300)) - n / 2 * (np.log(2 * np.pi) + 1)
    ev = np.where(best == len(grid) - 1, np.maximum(ev, limit), ev)
    beta = n / e_t
    return ev, np.exp(t) * beta, beta, where


def _ascend(values: np.ndarray, start: int) -> np.ndarray:
    """(C,) the grid index of the local maximum each column of values (G, C) climbs to from
    `start`: the maximum MacKay's fixed point (screen_version 2, from alpha = beta = 1, lam = 1)
    converged to where the evidence has more than one. A climb never turns (a step up to the
    right leaves a lower left neighbour): right first where the right neighbour is higher, else
    left where that one is, then on while the next is higher; found per column at once, not by
    one step of every column per pass (up to G passes)."""
    g, s = len(values), start
    rising = values[1:] > values[:-1]  # (G - 1, C): from i, i + 1 is higher
    falling = values[:-1] > values[1:]  # from i + 1, i is higher
    right = rising[s] if s + 1 < g else np.zeros(values.shape[1], bool)
    left = ~right & (falling[s - 1] if s > 0 else False)
    end = np.ones((1, values.shape[1]), bool)  # the grid's edge stops every climb
    up = s + np.argmax(np.concatenate([~rising[s:], end]), axis=0)  # first stop to the right
    down = s - np.argmax(np.concatenate([~falling[:s][::-1], end]), axis=0)  # to the left
    return np.where(right, up, np.where(left, down, s))


def _golden(lo: np.ndarray, hi: np.ndarray, sigma: np.ndarray, w: np.ndarray,
            unfit: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ln lam, evidence, E) (C,) at the maximum of each column's profile on [lo, hi] (C,):
    golden-section search, all columns together, GOLDEN_STEPS steps."""
    a, b = hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo)
    fa = _profile(np.exp(a), sigma, w, unfit, n)[0]
    fb = _profile(np.exp(b), sigma, w, unfit, n)[0]
    for _ in range(GOLDEN_STEPS):
        left = fa >= fb  # the maximum lies in [lo, b]: b's old point becomes the new a's twin
        lo, hi = np.where(left, lo, a), np.where(left, b, hi)
        a, b, fa, fb = (np.where(left, hi - GOLDEN * (hi - lo), b),
                        np.where(left, a, lo + GOLDEN * (hi - lo)),
                        np.where(left, 0.0, fb), np.where(left, fa, 0.0))
        fx = _profile(np.exp(np.where(left, a, b)), sigma, w, unfit, n)[0]
        fa, fb = np.where(left, fx, fa), np.where(left, fb, fx)
    t = np.where(fa >= fb, a, b)
    ev, e = _profile(np.exp(t), sigma, w, unfit, n)
    return t, ev, e
