"""REPORT.md's variance budget: where an encoder difference's uncertainty comes from, and what
it would take to resolve the leading pair (bench.analysis.budget)."""

from __future__ import annotations

from bench.analysis.budget import MAX_COUNT, Budget, variance_budget
from bench.report.context import ReportContext
from bench.report.format import num, table

TITLE = "Variance budget: what it would take to know"
LEVELS = ("release", "seed", "episode", "episode x training")

METHOD = (
    "Per backbone x suite, each encoder's paired per-episode difference to the leader, "
    "D[release, seed, episode], is split by method of moments into release, seed-within-release, "
    "held-out-episode and residual (episode x training, windows inside it) variance "
    "(bench/analysis/budget.py). The mean difference over R releases x S seeds x K episodes has "
    "variance V = s2_release/R + s2_seed/(RS) + s2_episode/K + s2_residual/(RSK); the shares "
    "below are each term's part of V at the measured counts (V itself scaled to the ranking's "
    "interval). For the leading pair, \"what it would take\" is the smallest R (or S, or K; "
    "the other two as measured, or all three scaled alike) at which 1.96 sqrt(V) < "
    "|observed gap|. Assumptions: the components hold at other counts, the "
    "observed gap is the true one (a smaller true gap needs more), effects independent and "
    "roughly normal, one native recipe (its releases' population)."
)


def budgets(ctx: ReportContext) -> list[Budget]:
    return [variance_budget(ctx.records, r) for r in ctx.rankings if r.encoders and not r.error]


def _needed(budget: Budget) -> str:
    if not budget.pairs:
        return ""
    first = budget.pairs[0]
    measured = dict(zip(("releases", "seeds", "episodes"), budget.counts))
    words = []
    for level, count in budget.needed.items():
        if count is None:
            words.append(f"no number of {level} alone (up to {MAX_COUNT:,})")
        elif count <= measured[level]:
            words.append(f"{level}: resolved at the measured {measured[level]}")
        else:
            words.append(f"{count} {level} (measured {measured[level]})")
    if budget.all_levels is not None and budget.all_levels > 1:
        r, s, k = (int(-(-n * budget.all_levels // 1)) for n in budget.counts)
        words.append(f"all three x{budget.all_levels:.3g} ({r} releases x {s} seeds x {k} "
                     "episodes)")
    elif budget.all_levels is None:
        words.append("not all three x100")
    return (f"**What it would take** ({budget.leader} vs {first.encoder}, gap "
            f"{num(first.gap, 3)}): " + "; or ".join(words) + ".")


def _share(value: float, unmeasured: bool) -> str:
    if unmeasured:  # one unit: its variance is in the others' and cannot be told apart
        return "not measured (one)"
    return f"{value:.0%}" if value == value else "n/a"


def budget_section(ctx: ReportContext) -> str | None:
    found = budgets(ctx)
    if not found:
        return None
    parts = [METHOD]
    for b in found:
        r, s, k = b.counts
        parts.append(f"### {b.backbone} x {b.suite} ({r} release{'s' if r != 1 else ''} x {s} "
                     f"seed{'s' if s != 1 else ''} x {k} held-out episodes; leader {b.leader})")
        unmeasured = {"release"} if r == 1 else set()
        unmeasured |= {"seed"} if s == 1 else set()
        rows = [[p.encoder, num(p.gap, 3), *(_share(p.shares[level], level in unmeasured)
                                             for level in LEVELS),
                 num(p.parts.df, 2)] for p in b.pairs]
        if rows:
            parts.append(table(rows, ["encoder", "Δ vs leader", "release", "seed", "episode",
                                      "episode x training", "Satterthwaite df"]))
            parts.append(_needed(b))
        if b.error:
            parts.append(f"_{b.error}_")
    return "\n\n".join(parts)
