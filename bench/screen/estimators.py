"""The screen proxies' numerics on frozen features: LogME, ridge and k-NN probes, norm entropy.

Pure functions, numpy in, float (or bench.stats.Undefined, with the reason) out. Two forms:
- from the windows themselves (`logme_windows`, `ridge_windows`, `knn_heldout`: what the screen
  runs): one decomposition per fitting set in the cheaper of its D x D and N x N forms
  (bench.screen.spectral), serving every target column and every ridge penalty;
- from `Moments`, the sufficient statistics X^T X, X^T Y, Y^T Y of X = [features, 1], which a
  caller accumulates chunk by chunk (`add`): memory flat in the windows, a D x D eigh per fit.
  Both give the same numbers (to rounding: tests/test_screening.py).
k-NN's distances are computed in chunks of queries, so its extra memory is (chunk, N_train).

Rules (stated in the report):
- The supervised proxies centre every column and scale every feature column to unit variance by
  the TRAINING windows' mean and standard deviation; a column constant on the training windows
  (relative variance <= 1e-10) carries nothing and is dropped. No column left: undefined.
- Ridge: the penalty is lambda = r * N_fit with r in RIDGE_GRID (N_fit: the fitting windows;
  the standardised Gram has diagonal N_fit), chosen by the smallest summed squared error of
  episode-wise folds of the training episodes (ties: the larger penalty), each fold predicted by
  a fit on the others scaled as all training windows are (screen_version 4: exact grouped
  cross-validation through a full fit's hat matrix, bench.screen.spectral.fold_errors); then
  refitted on all training episodes and scored on the held-out windows. k-NN: k in KNN_GRID
  (<= the fitting windows), chosen the same way; uniform mean of the k nearest (Euclidean,
  standardised).
- LogME (You et al., 2021) is the exact evidence, with every one of the D eigenvalues of
  F^T F in ln|A| (the reference's fast path drops (D - k) ln(alpha) and is wrong for D > N),
  maximised over (alpha, beta) in bounded work; a supremum at alpha/beta -> 0 or -> infinity is
  taken as its limit, and where each column's lay is kept (bench.screen.spectral).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import reduce

import numpy as np

from bench.screen.spectral import (CONSTANT_REL_VAR, ZERO_EIGEN_REL, Spectrum, fold_errors,
                                   knn_windows, logme_profile, spectrum)
from bench.stats import Measure, Undefined

RIDGE_GRID = tuple(float(r) for r in np.logspace(-4, 2, 13))
KNN_GRID = (1, 2, 3, 5, 8, 13, 21, 34, 55)
KNN_GRAM_MAX = 8192  # training windows up to which k-NN's folds share one N x N product (512 MB)


@dataclass
class Moments:
    """Sufficient statistics of (features (n, D), targets (n, C)): X = [features, 1],
    xtx (D+1, D+1), xty (D+1, C), yty (C,), float64; n = xtx[-1, -1]. Add chunks with `add`."""

    dim: int
    outputs: int
    xtx: np.ndarray = field(init=False)
    xty: np.ndarray = field(init=False)
    yty: np.ndarray = field(init=False)

    def __post_init__(self):
        self.xtx = np.zeros((self.dim + 1, self.dim + 1))
        self.xty = np.zeros((self.dim + 1, self.outputs))
        self.yty = np.zeros(self.outputs)

    @property
    def n(self) -> int:
        return int(round(self.xtx[-1, -1]))

    def add(self, features: np.ndarray, targets: np.ndarray) -> "Moments":
        """Accumulate a chunk: features (b, D), targets (b, C)."""
        x = np.concatenate([np.asarray(features, float), np.ones((len(features), 1))], axis=1)
        y = np.asarray(targets, float)
        self.xtx += x.T @ x
        self.xty += x.T @ y
        self.yty += (y * y).sum(axis=0)
        return self

    def plus(self, other: "Moments", sign: float = 1.0) -> "Moments":
        out = Moments(self.dim, self.outputs)
        out.xtx, out.xty = self.xtx + sign * other.xtx, self.xty + sign * other.xty
        out.yty = self.yty + sign * other.yty
        return out


def moments(features: np.ndarray, targets: np.ndarray, chunk: int = 4096) -> Moments:
    """Moments of features (N, D) and targets (N, C), read `chunk` rows at a time."""
    m = Moments(features.shape[1], targets.shape[1])
    for start in range(0, len(features), chunk):
        m.add(features[start:start + chunk], targets[start:start + chunk])
    return m


@dataclass
class Standardised:
    """Training-standardised statistics: gram (d, d) = Z^T Z, zy (d, C) = Z^T Yc, yy (C,) =
    column sums of Yc^2, over n windows; `keep` (D,) bool, `mean`, `scale` (D,), `ymean` (C,)."""

    n: int
    gram: np.ndarray
    zy: np.ndarray
    yy: np.ndarray
    keep: np.ndarray
    mean: np.ndarray
    scale: np.ndarray
    ymean: np.ndarray


def standardise(m: Moments, frame: Standardised | None = None) -> Standardised | Undefined:
    """Centre by `m`'s own windows and scale by them, dropping constant columns (undefined if
    none vary); or scale and drop as `frame` (all fitting windows' standardisation) does: what
    ridge's fold fits do (see spectral.fold_errors)."""
    n, d = m.n, m.dim
    if n < 2:
        return Undefined(f"{n} fitting window(s): too few windows")
    mean, ymean = m.xtx[:d, -1] / n, m.xty[-1] / n
    cov = m.xtx[:d, :d] - n * np.outer(mean, mean)
    if frame is not None:
        keep, scale = frame.keep, frame.scale
    else:
        var = np.diag(cov) / n
        keep = var > CONSTANT_REL_VAR * np.maximum(np.diag(m.xtx)[:d] / n, 1e-300)
        if not keep.any():
            return Undefined(f"all {d} feature columns constant over the {n} fitting windows")
        scale = np.where(keep, np.sqrt(np.where(keep, var, 1.0)), 1.0)
    k = keep
    gram = cov[np.ix_(k, k)] / np.outer(scale[k], scale[k])
    zy = (m.xty[:d][k] - n * np.outer(mean[k], ymean)) / scale[k, None]
    yy = m.yty - n * ymean ** 2
    return Standardised(n, gram, zy, yy, keep, mean, scale, ymean)


def logme_columns(sigma: np.ndarray, z: np.ndarray, yy: np.ndarray, n: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(maximised log evidence per sample, alpha, beta), each (C,), from the nonzero eigenvalues
    `sigma` (r,) of F^T F and z = V^T F^T Y (r, C): every eigenvalue enters ln|A|, so D > N is
    exact. Maximised in bounded work (bench.screen.spectral.logme_profile); where D >= N the
    optimum can lie at beta -> infinity (a noise-free fit), where the features explain nothing at
    alpha -> infinity: the evidence is then its limit there."""
    ev, alpha, beta, _ = logme_profile(sigma, z, yy, n)
    return ev / n, alpha, beta


def _spectrum(gram: np.ndarray, fty: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nonzero eigenvalues (d,) of F^T F (D, D) and z = V^T F^T Y (d, C) on their vectors.
    A zero eigenvalue adds ln(alpha) / 2 to the evidence and takes it away again, and its z is
    zero: the evidence is exact without it, and with D > N most of the D eigenvalues are zero."""
    sigma, vecs = np.linalg.eigh(gram)
    if sigma.max() <= 0:
        return sigma[:0], fty[:0]
    rank = sigma > ZERO_EIGEN_REL * sigma.max()
    return sigma[rank], vecs[:, rank].T @ fty


def logme_gram(gram: np.ndarray, fty: np.ndarray, yty: np.ndarray, n: int) -> Measure:
    """Mean over the C target columns of LogME from F^T F (D, D), F^T Y (D, C), Y^T Y diag (C,),
    `n` the dimension the targets live in (the windows, less one where both are centred)."""
    if n < 2:
        return Undefined(f"{n} window(s): too few windows")
    return logme_spectrum(*_spectrum(gram, fty), yty, n)[0]


def logme_spectrum(sigma: np.ndarray, z: np.ndarray, yy: np.ndarray, n: int
                   ) -> tuple[Measure, str | None]:
    """(mean over the target columns of LogME, where the optima lie: "interior 340, lam->0 10")
    from the nonzero eigenvalues sigma (r,), z (r, C), yy (C,) in `n` dimensions."""
    if not np.any(yy > 0):
        return Undefined("every target column is zero"), None
    if len(sigma) == 0:
        return Undefined("features are all zero"), None
    live = yy > 0
    ev, _, _, where = logme_profile(sigma, z[:, live], yy[live], n)
    value = float(np.mean(ev / n))
    counts = ", ".join(f"{k} {where.count(k)}" for k in dict.fromkeys(sorted(where)))
    if not np.isfinite(value):
        return Undefined(f"LogME's evidence is not finite ({value})"), counts
    return value, counts


def logme_windows(train: np.ndarray, targets: np.ndarray, spec: Spectrum | Undefined | None = None
                  ) -> tuple[Measure, str | None]:
    """The screen's LogME (logme_moments) from the windows (N, D), (N, C) themselves, through
    the cheaper of the D x D and N x N decompositions (`spec`: that Spectrum, if made already);
    also where the optima lie (logme_spectrum)."""
    spec = spectrum(train, targets) if spec is None else spec
    if isinstance(spec, Undefined):
        return spec, None
    if spec.n - 1 < 2:
        return Undefined(f"{spec.n} fitting window(s): too few windows"), None
    return logme_spectrum(spec.sigma, spec.z, spec.yy, spec.n - 1)


def logme_fit(features: np.ndarray, targets: np.ndarray) -> list[tuple[float, float, float]]:
    """Per target column (log evidence per sample, alpha, beta) at LogME's optimum; features
    (N, D), targets (N, C), as given. For checks against an explicit N x N evidence."""
    f, y = np.asarray(features, float), np.asarray(targets, float)
    sigma, z = _spectrum(f.T @ f, f.T @ y)
    ev, alpha, beta = logme_columns(sigma, z, (y * y).sum(axis=0), len(f))
    return list(zip(ev.tolist(), alpha.tolist(), beta.tolist()))


def logme(features: np.ndarray, targets: np.ndarray) -> Measure:
    """LogME of features (N, D) for targets (N, C), as given (no centring): the mean over target
    columns of the maximised log evidence per sample; exact for N < D as for N > D."""
    f, y = np.asarray(features, float), np.asarray(targets, float)
    return logme_gram(f.T @ f, f.T @ y, (y * y).sum(axis=0), len(f))


def logme_moments(m: Moments) -> Measure:
    """The screen's LogME: of the training-standardised features for the centred targets.
    Centring leaves the targets and features n - 1 dimensions (all orthogonal to the ones
    vector): the evidence is taken there. Over all n, the noise variance along the ones vector
    could shrink to zero for free once features span the rest (D >= n - 1): beta -> infinity
    and an evidence without bound (NaN in float64)."""
    s = standardise(m)
    if isinstance(s, Undefined):
        return s
    return logme_gram(s.gram, s.zy, s.yy, s.n - 1)


def ridge_path(m: Moments, ratios: tuple[float, ...], frame: Standardised | None = None
               ) -> list[tuple[np.ndarray, np.ndarray]] | Undefined:
    """Per ratio (weights (D, C), bias (C,)) in raw feature units: ridge on `m`'s standardised
    windows, penalty ratio * n, bias unpenalised (the centring); one eigh for all ratios.
    `frame`: scaled as all fitting windows are (a fold fit; see spectral.fold_errors)."""
    s = standardise(m, frame)
    if isinstance(s, Undefined):
        return s
    sigma, vecs = np.linalg.eigh(s.gram)
    rotated = vecs.T @ s.zy
    out = []
    for ratio in ratios:
        wz = vecs @ (rotated / (np.clip(sigma, 0.0, None) + ratio * s.n)[:, None])
        weights = np.zeros((m.dim, m.outputs))
        weights[s.keep] = wz / s.scale[s.keep, None]
        out.append((weights, s.ymean - s.mean @ weights))
    return out


def ridge_fit(m: Moments, ratio: float) -> tuple[np.ndarray, np.ndarray] | Undefined:
    """(weights (D, C), bias (C,)) of ridge at one penalty ratio (see ridge_path)."""
    path = ridge_path(m, (ratio,))
    return path if isinstance(path, Undefined) else path[0]


def squared_error(m: Moments, weights: np.ndarray, bias: np.ndarray) -> float:
    """Sum over `m`'s windows and columns of (features @ weights + bias - targets)^2, from m."""
    w = np.concatenate([weights, bias[None, :]], axis=0)
    return float(np.trace(w.T @ m.xtx @ w) - 2 * np.sum(w * m.xty) + m.yty.sum())


def ridge_heldout(folds: list[Moments], heldout: Moments) -> tuple[Measure, float | None]:
    """(held-out MSE per target element, chosen penalty ratio) of ridge; `folds` are the
    training windows grouped by episode fold (>= 2), `heldout` the scored windows."""
    if len(folds) < 2:
        return Undefined(f"{len(folds)} training episode fold(s): the penalty cannot be chosen "
                         "on training episodes"), None
    total = reduce(Moments.plus, folds)  # f0 + f1 + ..., in fold order
    frame = standardise(total)
    if isinstance(frame, Undefined):
        return frame, None
    errors = np.zeros(len(RIDGE_GRID))
    for f in folds:
        path = ridge_path(total.plus(f, -1.0), RIDGE_GRID, frame)
        if isinstance(path, Undefined):
            return path, None
        errors += [squared_error(f, *fit) for fit in path]
    best = max(i for i, e in enumerate(errors) if e <= min(errors))  # ties: the larger penalty
    fit = ridge_fit(total, RIDGE_GRID[best])
    if isinstance(fit, Undefined):
        return fit, None
    if heldout.n == 0:
        return Undefined("no held-out windows"), RIDGE_GRID[best]
    return squared_error(heldout, *fit) / (heldout.n * heldout.outputs), RIDGE_GRID[best]


def ridge_windows(train: np.ndarray, targets: np.ndarray, fold: np.ndarray,
                  heldout: np.ndarray, heldout_targets: np.ndarray,
                  spec: Spectrum | Undefined | None = None) -> tuple[Measure, float | None]:
    """ridge_heldout from the windows themselves: train (N, D), targets (N, C), fold (N,) the
    episode fold of each (>= 2), heldout (M, D), (M, C); `spec` the Spectrum of all training
    windows if made already; the folds' errors at every penalty: spectral.fold_errors."""
    folds = np.unique(fold)
    if len(folds) < 2:
        return Undefined(f"{len(folds)} training episode fold(s): the penalty cannot be chosen "
                         "on training episodes"), None
    fit = spectrum(train, targets) if spec is None else spec
    if isinstance(fit, Undefined):
        return fit, None
    errors = fold_errors(fit, targets, fold, RIDGE_GRID)
    best = max(i for i, e in enumerate(errors) if e <= min(errors))  # ties: the larger penalty
    if len(heldout) == 0:
        return Undefined("no held-out windows"), RIDGE_GRID[best]
    error = ((fit.predict(fit.project(heldout), RIDGE_GRID[best]) - heldout_targets) ** 2).sum()
    return float(error / np.size(heldout_targets)), RIDGE_GRID[best]


def _knn_sse(queries: np.ndarray, query_targets: np.ndarray, reference: np.ndarray,
             reference_targets: np.ndarray, ks: tuple[int, ...], chunk: int,
             ref_sq: np.ndarray | None = None) -> np.ndarray:
    """(len(ks),) _nearest_sse from chunks of `queries` (q, d) to `reference` (r, d);
    ref_sq: (reference ** 2).sum(axis=1) if computed already."""
    ref_sq = (reference ** 2).sum(axis=1) if ref_sq is None else ref_sq
    sse = np.zeros(len(ks))
    for start in range(0, len(queries), chunk):
        q = queries[start:start + chunk]
        dist = (q ** 2).sum(axis=1)[:, None] - 2 * q @ reference.T + ref_sq[None, :]
        _nearest_sse(dist, query_targets[start:start + chunk], reference_targets, ks, sse)
    return sse


def _nearest_sse(dist: np.ndarray, truth: np.ndarray, reference_targets: np.ndarray,
                 ks: tuple[int, ...], sse: np.ndarray) -> None:
    """Add to sse (len(ks),) the squared error against `truth` (b, C) of each query's mean k
    nearest reference targets by `dist` (b, r); of windows tied at the k-th distance, numpy's
    argpartition's (deterministic) choice."""
    kmax = max(ks)
    if kmax < dist.shape[1]:  # the kmax nearest, then in order (a full sort is N log N)
        near = np.argpartition(dist, kmax - 1, axis=1)[:, :kmax]
        order = np.argsort(np.take_along_axis(dist, near, axis=1), axis=1, kind="stable")
        nearest = np.take_along_axis(near, order, axis=1)
    else:
        nearest = np.argsort(dist, axis=1, kind="stable")
    running = np.zeros_like(truth)  # no (b, kmax, C) cumsum: most of k-NN's time at C = 350
    for j in range(kmax):
        running += reference_targets[nearest[:, j]]
        if j + 1 in ks:
            sse[ks.index(j + 1)] += float(((running / (j + 1) - truth) ** 2).sum())


def _knn_fold_sse(z: np.ndarray, y: np.ndarray, fold: np.ndarray, ks: tuple[int, ...],
                  chunk: int, sq: np.ndarray, gram: np.ndarray | None) -> np.ndarray:
    """(len(ks),) k-NN's squared error, each episode fold predicted from the others; sq (N,):
    z's squared row norms. Up to KNN_GRAM_MAX windows the distances are blocks of one N x N z z^T
    (`gram`, if made already) and sq: gathering z's rows per fold cost more than the search."""
    if len(z) > KNN_GRAM_MAX:
        return sum(_knn_sse(z[fold == f], y[fold == f], z[fold != f], y[fold != f], ks, chunk)
                   for f in np.unique(fold))
    sse, gram = np.zeros(len(ks)), z @ z.T if gram is None else gram
    for f in np.unique(fold):
        inside, rest = np.flatnonzero(fold == f), np.flatnonzero(fold != f)
        for start in range(0, len(inside), chunk):
            q = inside[start:start + chunk]
            dist = sq[q][:, None] - 2 * gram[np.ix_(q, rest)] + sq[rest][None, :]
            _nearest_sse(dist, y[q], y[rest], ks, sse)
    return sse


def knn_heldout(train_features: np.ndarray, train_targets: np.ndarray, train_fold: np.ndarray,
                heldout_features: np.ndarray, heldout_targets: np.ndarray, chunk: int = 512,
                weights: np.ndarray | None = None, spec: Spectrum | Undefined | None = None
                ) -> tuple[Measure, int | None]:
    """(held-out MSE per target element, chosen k) of k-NN regression.

    train_features (N, D), train_targets (N, C), train_fold (N,) int: the episode fold of each
    training window (>= 2 folds; k chosen on them), heldout_* (M, D), (M, C); weights (D,): a
    factor on each standardised column in the distance (default 1); `spec`: the training
    windows' Spectrum, if made already (its standardisation: spectral.knn_windows)."""
    folds, sizes = np.unique(train_fold, return_counts=True)
    if len(folds) < 2:
        return Undefined(f"{len(folds)} training episode fold(s): k cannot be chosen on "
                         "training episodes"), None
    if len(heldout_features) == 0:
        return Undefined("no held-out windows"), None
    standard = knn_windows(train_features, weights, spec)
    if isinstance(standard, Undefined):
        return standard, None
    (scale, z, gram), y = standard, np.asarray(train_targets, float)
    ks = tuple(k for k in KNN_GRID if k <= len(train_fold) - sizes.max())  # <= every fit set
    sq = (z ** 2).sum(axis=1)  # _knn_sse's own expression: the held-out scores' bits
    sse = _knn_fold_sse(z, y, train_fold, ks, chunk, sq, gram)
    k = ks[int(np.argmin(sse))]  # ties: the smaller k (argmin's first)
    heldout_sse = _knn_sse(scale(heldout_features), np.asarray(heldout_targets, float), z, y,
                           (k,), chunk, sq)[0]
    return float(heldout_sse / heldout_targets.size), k


def token_norms(grid: np.ndarray) -> np.ndarray:
    """Per-token L2 norms (N, h*w) of a token grid (N, C, h, w)."""
    grid = np.asarray(grid, float)
    return np.sqrt((grid ** 2).sum(axis=1)).reshape(len(grid), -1)


def norm_entropy(norms: np.ndarray) -> Measure:
    """Theia-style feature-norm entropy, label-free, in [0, 1]: per window, the Shannon entropy of
    its tokens' norms normalised to a distribution, divided by ln(tokens); mean over windows.

    norms (N, T) >= 0 (token_norms). 1 means every token has the same norm (no token stands out),
    lower means a few tokens carry most of the norm. Windows whose norms are all 0 are skipped."""
    norms = np.asarray(norms, float)
    if norms.ndim != 2 or norms.shape[1] < 2:
        return Undefined(f"needs (N, T) norms with T >= 2 tokens; got shape {norms.shape}")
    total = norms.sum(axis=1)
    live = total > 0
    if not live.any():
        return Undefined("every token norm is 0")
    p = norms[live] / total[live, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -np.where(p > 0, p * np.log(p), 0.0).sum(axis=1)
    return float(np.mean(h / np.log(norms.shape[1])))
