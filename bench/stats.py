"""Statistics that the simulator (bench/sim) and the analysis (bench/analysis) both use: a leaf
module below both, importing nothing of graftbench's."""

from __future__ import annotations


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
