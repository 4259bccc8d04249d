"""REPORT.md text for the screen tier: the screen table and each tier's agreement with the graft.

Pure: lists of bench.run.screen.ScreenScores and bench.analysis.tiers.TierAgreement in, markdown
out. Not yet called by the report builder (the --screen workflow that produces them is not
wired in); an undefined value prints as "undefined: <reason>", never as a number."""

from __future__ import annotations

from typing import Sequence

from bench.analysis.agreement import STATISTICS, TIE_RULE, Interval, Undefined
from bench.report.format import num, table

PROXIES = ("logme", "ridge", "knn")


def measure(value, digits: int = 4) -> str:
    """A number, or 'undefined: reason'."""
    return f"undefined: {value.reason}" if isinstance(value, Undefined) else num(value, digits)


def screen_table(screens: Sequence) -> str:
    """One row per screened (backbone, suite, encoder): each supervised proxy's gain of the
    features over the state, ridge and k-NN held-out MSE with features, the entropy, seconds."""
    rows = [[s.backbone, s.suite, s.encoder]
            + [measure(s.proxies[p]["gain"]) for p in PROXIES]
            + [measure(s.proxies["ridge"]["state+features"]),
               measure(s.proxies["knn"]["state+features"]), measure(s.entropy, 3),
               num(s.seconds, 2)]
            for s in sorted(screens, key=lambda s: (s.backbone, s.suite, s.encoder))]
    return table(rows, ["backbone", "suite", "encoder", "LogME gain", "ridge gain", "k-NN gain",
                        "ridge MSE", "k-NN MSE", "entropy", "s"])


def _with_interval(point, interval) -> str:
    text = measure(point, 3)
    if isinstance(interval, Interval):
        text += f" [{num(interval.low, 3)}, {num(interval.high, 3)}]"
    return text


def agreement_table(agreements: Sequence) -> str:
    """One row per (backbone, suite, cheaper tier) with the point statistic and its paired
    window bootstrap interval, or why it was not measured; then the tie rule."""
    rows = []
    for a in agreements:
        head = [a.backbone, a.suite, a.tier, len(a.encoders)]
        if a.missing or a.point is None:
            rows.append(head + [a.missing or "not measured"] + [""] * (len(STATISTICS) - 1))
            continue
        rows.append(head + [_with_interval(getattr(a.point, k), a.intervals.get(k))
                            for k in STATISTICS])
    return (table(rows, ["backbone", "suite", "tier", "encoders", "Kendall tau-b",
                         "weighted tau", "MMRV (MSE)", "top-1 regret (MSE)"])
            + f"\n\nTies: {TIE_RULE}")
