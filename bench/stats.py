"""Statistics that the simulator (bench/sim), the analysis (bench/analysis) and the stored screen
records (bench/results) use: a leaf module below them, importing nothing of graftbench's."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Union


@dataclass(frozen=True)
class Undefined:
    """A statistic that has no value on these inputs, and why (never a NaN inside a ranking)."""

    reason: str

    def __float__(self) -> float:
        return float("nan")

    def __str__(self) -> str:
        return f"undefined ({self.reason})"


Measure = Union[float, Undefined]


def is_defined(x: Measure) -> bool:
    """True when `x` is a number, False when it is `Undefined`."""
    return not isinstance(x, Undefined)


def as_float(x: Measure) -> float:
    """`x` as a float for numeric consumers (plots, JSON): NaN when undefined."""
    return float(x)


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion `successes` / `n` (scipy), as (low, high).

    n == 0 gives (0.0, 1.0): with no trial every rate is consistent with the data, and it is the
    limit of Wilson's own formula as n -> 0 (centre 1/2, half-width 1/2). Unlike (nan, nan) it
    stays valid JSON in the rollout results bench/sim writes, and it is what they always held.
    """
    from scipy.stats import binomtest

    if n == 0:
        return 0.0, 1.0
    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence,
                                                          method="wilson")
    return float(ci.low), float(ci.high)
