"""Screen inputs at the real study's size without an encoder: the screen's benchmark
(benchmarks/bench_screen.py) and its tolerance tests read them.

The study's real encoders screen N = 721 training windows (5 episode folds) and ~144 held-out
ones, D = 2,568 feature columns (two cameras x 1,284 pooled channels) plus the 8 state columns,
C = 350 targets (a 50-step chunk x 7 action dims). Here a latent task state h (smooth along each
episode) drives the robot state and the action chunk; the features are ReLU units of a
low-rank mixture (as pooled CNN channels are: non-negative, correlated) of h where `signal`, or of
an independent latent of the same kind where not (an encoder whose features carry nothing about
the task, as the random-init twin's did).
"""

from __future__ import annotations

import numpy as np

from bench.screen.proxies import FitInputs

LATENT = 12  # the task state's dimensions
EPISODE = 18  # windows per episode (721 windows: ~40 episodes)


def _latent(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, LATENT) random walks restarted every EPISODE windows, unit-ish scale."""
    steps = rng.normal(size=(n, LATENT)) * 0.3
    h = np.zeros((n, LATENT))
    for i in range(n):
        h[i] = steps[i] + (h[i - 1] if i % EPISODE else rng.normal(size=LATENT))
    return h


def _windows(n: int, signal: bool, dims: tuple[int, int, int], mixes: tuple[np.ndarray, ...],
             rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(inputs (n, 8 + D) float32 = [state, features], targets (n, C) float32)."""
    d, state_dim, c = dims
    to_feat, to_target = mixes
    h = _latent(n, rng)
    seen = h if signal else _latent(n, rng)
    state = h[:, :state_dim] + 0.1 * rng.normal(size=(n, state_dim))
    features = np.maximum(seen @ to_feat + 0.3 * rng.normal(size=(n, d)), 0.0)
    targets = np.tanh(h @ to_target) + 0.2 * rng.normal(size=(n, c))
    return (np.concatenate([state, features], axis=1).astype(np.float32),
            targets.astype(np.float32))


def synthetic_fit(signal: bool = True, n: int = 721, m: int = 144, d: int = 2568,
                  c: int = 350, folds: int = 5, seed: int = 0) -> FitInputs:
    """The [state, features] FitInputs of one synthetic screen (see the module doc)."""
    rng = np.random.default_rng(seed)
    state_dim = 8
    mixes = (rng.normal(size=(LATENT, d)) / np.sqrt(LATENT),
             rng.normal(size=(LATENT, c)) / np.sqrt(LATENT))
    train, y = _windows(n, signal, (d, state_dim, c), mixes, rng)
    held, y_held = _windows(m, signal, (d, state_dim, c), mixes, rng)
    fold = (np.arange(n) // EPISODE) % folds
    weights = np.concatenate([np.full(state_dim, state_dim ** -0.5), np.full(d, d ** -0.5)])
    return FitInputs(train, y, fold, held, y_held, weights)
