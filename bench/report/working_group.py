"""REPORT.md's verdict within the working group (bench.analysis.working_group): the candidates
that work, in closed-loop order with intervals, and offline MSE's agreement with that order."""

from __future__ import annotations

import json
import math

from bench.analysis.agreement import Interval, Undefined
from bench.analysis.rankings import CONFIDENCE
from bench.analysis.sequential_study import DESIGN_FILE, order_line
from bench.analysis.working_group import OPEN_PAIR_RULE, WORKING_RULE, WorkingGroup
from bench.report.context import ReportContext
from bench.report.format import interval, num, table

TITLE = "Closed loop: the verdict within the working group"
INTRO = (
    "Which of the encoders that work succeeds most, and does offline MSE tell? " + WORKING_RULE
    + " Success per item is the mean over its cells (releases x seeds) of each cell's share of "
    "successful episodes; intervals draw releases, seeds within a release and rollout episodes "
    "within their task (across tasks where a task holds one; n - 1 of n at each level, one draw "
    "for every item: an episode is a task and init state, the same for every item), "
    f"percentile, {CONFIDENCE:.0%}. A neighbour pair "
    "is compared on the episodes both items ran; it is resolved when the interval of its "
    "difference excludes 0. Kendall tau-b of -MSE and success over the working items, with the "
    "same draw (held-out windows for the MSE, the cell draw shared): +1 is 'offline MSE orders "
    "the working group as the closed loop does'. " + OPEN_PAIR_RULE + " These are fixed-sample "
    "intervals; a sequential study's own declarations (anytime-valid) are in its design file.")


def _pct(pair) -> str:
    return f"[{100 * pair[0]:.0f}, {100 * pair[1]:.0f}]"


def _more(pair) -> str:
    if pair.resolved:
        return ""
    if math.isinf(pair.more):
        return "no size (no observed difference)"
    if pair.more == 0:
        return f"0 (McNemar's {math.ceil(pair.needed)} reached: seeds or releases hold it open)"
    return f"{pair.more} ({math.ceil(pair.needed)} in all)"


def items_table(wg: WorkingGroup) -> str:
    rows = [[s.item, "yes" if s.candidate else "no",
             "**yes**" if s.working else ("reference" if s.item == wg.reference else "no"),
             s.cells, s.episodes, f"{s.success:.1%}", _pct(s.ci), num(s.mse)]
            for s in wg.items]
    return table(rows, ["item", "candidate", "working", "cells", "episodes", "success",
                        f"{CONFIDENCE:.0%} CI", "norm. MSE"])


def pairs_table(wg: WorkingGroup) -> str:
    rows = [[f"{p.upper} - {p.lower}", p.paired_episodes,
             f"{p.upper_only:.1%} / {p.lower_only:.1%}", f"{100 * p.diff:+.1f} pts",
             interval((100 * p.ci[0], 100 * p.ci[1]), 3), "yes" if p.resolved else "**open**",
             "yes" if p.mse_agrees else "no", _more(p)] for p in wg.pairs]
    return table(rows, ["neighbours (upper - lower)", "paired episodes",
                        "only upper / only lower succeeded", "success difference",
                        f"{CONFIDENCE:.0%} CI (pts)", "resolved", "MSE orders them so",
                        "more paired episodes it needs"])


def verdict_line(wg: WorkingGroup) -> str:
    """The group's order, its resolved pairs, tau-b with its interval, and what stays open."""
    if not wg.order:
        return "No candidate is measured to work here: no order within a working group."
    tau = (str(wg.tau_b) if isinstance(wg.tau_b, Undefined) else
           f"{wg.tau_b:.2f} " + (interval((wg.tau_b_ci.low, wg.tau_b_ci.high), 2)
                                 if isinstance(wg.tau_b_ci, Interval) else f"({wg.tau_b_ci})"))
    resolved = [p for p in wg.pairs if p.resolved]
    agree = sum(p.mse_agrees for p in resolved)
    open_pairs = wg.open_pairs
    order = wg.order[0] + "".join((" > " if p.resolved else " ~ ") + p.lower for p in wg.pairs)
    text = (f"Closed-loop order of the {len(wg.order)} working item(s) ('>' resolved, '~' open): "
            f"{order}. Kendall tau-b of -MSE and success among them: {tau}; offline MSE orders "
            f"{agree} of the {len(resolved)} resolved neighbour pair(s) the same way.")
    if open_pairs:
        finite = [p.more for p in open_pairs if math.isfinite(p.more)]
        text += (f" {len(open_pairs)} pair(s) stay open"
                 + (f"; the most any needs: {max(finite)} more paired episodes"
                    if finite else "") + ".")
    return text


def design_line(ctx: ReportContext) -> str | None:
    """The sequential design the results folder was run under, and why it stopped; None: none."""
    path = ctx.results.root / DESIGN_FILE
    try:
        study = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    design, last = study.get("design", {}), study.get("last", {})
    spent = last.get("spent_episodes")
    # The design's own order: its declarations are anytime-valid, the tables' intervals are not.
    order = (f" Its order ('>' declared, '~' open; ties in success keep the --items order): "
             f"{order_line(last)}." if last.get("order") and "pairs" in last else "")
    return (f"Run as a sequential study ({DESIGN_FILE}: {design.get('rule', '?')}, alpha "
            f"{design.get('alpha', '?')}, budget {design.get('budget', '?')} episodes, "
            f"{design.get('units_per_round', '?')} episodes per item a round): "
            f"{last.get('rounds', '?')} round(s), stopped: {last.get('stop') or 'not yet'}"
            + (f"; {spent} episodes rolled out in all" if spent is not None else "") + "."
            + order)


def working_group_section(ctx: ReportContext) -> str | None:
    groups = [wg for wg in ctx.working_groups if wg.items or wg.missing]
    if not groups:
        return None
    parts = [INTRO]
    if (line := design_line(ctx)) is not None:
        parts.append(line)
    for wg in groups:
        head = f"**{wg.backbone} x {wg.suite}**"
        if wg.missing:
            parts.append(f"{head}: _no verdict: {wg.missing}._")
            continue
        parts.append(f"{head} (reference: {wg.reference or 'success 0'})\n\n{items_table(wg)}")
        if wg.pairs:
            parts.append(pairs_table(wg))
        parts.append(verdict_line(wg))
    return "\n\n".join(parts)
