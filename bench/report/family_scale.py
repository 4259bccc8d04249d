"""REPORT.md's "Family or scale" section: over a grid of the tiny size ladder, does the encoder
ranking change with the backbone's size, its family, both or neither (bench.analysis.family_scale),
by how much, and what screening on the family's small model buys (its agreement with the family's
largest size and its cost). Pure: the analyses in the context in, markdown out; None when the
records hold no comparison (the report leaves the section out)."""

from __future__ import annotations

from typing import Sequence

from backbones.tiny_sizes import size_of
from bench.analysis.family_scale import CHANGE_RULE, FAMILY, SIZE, Comparison, SuiteVerdict
from bench.analysis.tiers import SMALL_MODEL
from bench.report.context import ReportContext
from bench.report.format import interval, num, pct, table, yes_no
from bench.report.screen import agreement_table
from bench.report.screen_cost import (SMALL_MODEL_COST_HEADERS, SMALL_MODEL_COST_TEXT,
                                      small_model_cost_rows)

TITLE = "Family or scale"
INTRO = (
    "The study's two backbones differ in family and in size at once. Here each family is "
    "measured at several sizes of the tiny ladder (backbones/tiny_sizes.py: the language model "
    "and action expert scaled, the vision tower, token grid and prompt the family's own; sizes "
    "s, m, l matched across families by width, depth and attention shapes, pi0.5 holding "
    "1.21-1.22x SmolVLA's parameters at each). **Size**: each smaller size against its family's "
    "largest (choose on the small model, deploy on the large). **Family**: SmolVLA against "
    "pi0.5 at each matched size. Every figure is on {items}; intervals: the rankings' "
    "hierarchical bootstrap (releases, seeds, held-out episodes, windows), both backbones of a "
    "comparison drawn on the same episodes, percentile. Tiny sizes are not 450M or 3.3B: the "
    "ladder spans {span} within a family, far below either real release."
)
VERDICT_WORDS = {SIZE: "changes with size, not with family", FAMILY: "changes with family, not "
                 "with size", "both": "changes with size and with family", "neither": "changes "
                 "with neither size nor family"}


def _params(name: str) -> str:
    size = size_of(name)
    return f"{name} ({size.params / 1e6:.2f}M)" if size else name


def _with_ci(value, pair, digits: int = 3) -> str:
    return f"{num(value, digits)} {interval(pair, digits)}"


def _regret(value, pair) -> str:
    return pct(value) + (f" [{pct(pair[0])}, {pct(pair[1])}]" if pair else "")


def comparison_row(c: Comparison) -> list[str]:
    t, a = c.transfer, c.transfer.agreement
    if not t.complete:
        head = [t.suite, c.axis, f"{_params(t.small)} -> {_params(t.large)}", t.missing]
        return head + [""] * (len(COMPARISON_HEADERS) - len(head))
    return [t.suite, c.axis, f"{_params(t.small)} -> {_params(t.large)}", str(len(t.encoders)),
            _with_ci(a.get("tau_b"), a.get("tau_b_ci")), num(a.get("weighted_tau"), 3),
            f"{t.small_winner} / {t.large_winner}", ", ".join(c.small_tier),
            ", ".join(c.large_tier), yes_no(t.large_winner_in_small_tier),
            _regret(a.get("top1_regret"), a.get("top1_regret_ci")),
            _regret(a.get("top1_regret_back"), a.get("top1_regret_back_ci")),
            yes_no(c.changes)]


COMPARISON_HEADERS = ["suite", "axis", "source -> target (parameters)", "n", "tau-b [95% CI]",
                      "weighted tau", "leaders (source / target)", "source top tier",
                      "target top tier", "source tier holds the target's leader",
                      "top-1 regret source -> target [CI]", "target -> source [CI]",
                      "changes the choice"]


def verdict_line(v: SuiteVerdict) -> str:
    words = VERDICT_WORDS.get(v.verdict, v.verdict)
    how = {axis: [c for c in v.on(axis) if c.changes] for axis in (SIZE, FAMILY)}
    which = "; ".join(f"{axis}: {len(how[axis])} of {len(v.on(axis))} comparisons change the "
                      "choice" for axis in (SIZE, FAMILY) if v.on(axis))
    outside = f" (not compared: {', '.join(v.outside)}, outside the ladder)" if v.outside else ""
    return f"- **{v.suite}** (on {v.items}): the ranking {words} ({which}){outside}."


def small_model_rows(ctx: ReportContext) -> list:
    """The small-model rung's TierAgreements: the screen's (beside its naive baselines) where
    the large model's panel was screened, the family analysis's elsewhere."""
    screened = [a for a in ctx.screen_agreements if a.tier.startswith(SMALL_MODEL)]
    panels = {(a.backbone, a.suite) for a in screened}
    return screened + [a for a in ctx.small_model if (a.backbone, a.suite) not in panels]


def family_scale_section(ctx: ReportContext) -> str | None:
    """The section, or None when no suite holds a comparison."""
    verdicts = ctx.family_scale
    if not verdicts:
        return None
    sizes = [size_of(r.backbone) for r in ctx.records if size_of(r.backbone) is not None]
    families = {s.family for s in sizes}
    spans = [max(s.params for s in sizes if s.family == f)
             / min(s.params for s in sizes if s.family == f) for f in sorted(families)]
    items = sorted({v.items for v in verdicts})
    parts = [INTRO.format(items=" / ".join(items),
                          span="x" + " / x".join(f"{r:.0f}" for r in spans)),
             CHANGE_RULE, "\n".join(verdict_line(v) for v in verdicts),
             table([comparison_row(c) for v in verdicts for c in v.comparisons],
                   COMPARISON_HEADERS)]
    rungs = small_model_rows(ctx)
    if rungs:
        with_naive = all(a.naive_gap is not None or a.missing for a in rungs)
        parts += ["**Screen on the small model of the family**: the small model's graft MSE as "
                  "a cheaper tier for the family's largest (the screen's agreement table, "
                  "same statistics and draws" + ("" if with_naive else "; no screen stored "
                  "here, so no naive baselines beside it") + ")",
                  agreement_table(rungs, with_naive)]
    cost = small_model_cost_rows(ctx.records)
    if cost:
        parts += [SMALL_MODEL_COST_TEXT, table(cost, SMALL_MODEL_COST_HEADERS)]
    return "\n\n".join(parts)
