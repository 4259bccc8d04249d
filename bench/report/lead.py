"""The report's first lines: the answer to the run it was given. Per backbone x suite, the
winner, its top tier (the near-tie band) and its margin over the next encoder with the paired
interval; then, only where both backbones of a suite ran, whether the small backbone's winner
transfers; then what undermines either (a ranking that measures no vision)."""

from __future__ import annotations

from collections import Counter

from bench.analysis.rankings import CONFIDENCE, PRIMARY, Ranking
from bench.report.context import ReportContext
from bench.report.format import interval, num


def ranking_answer(r: Ranking, ctx: ReportContext) -> str:
    """One line: who leads `r`'s backbone x suite, by how much, and how sure."""
    where = f"**{r.backbone} x {r.suite}**"
    if r.error or not r.encoders:
        return f"{where}: not ranked ({r.error or 'no graft'})."
    lead = r.encoders[0]
    score = f"norm. MSE {num(lead.mean[PRIMARY])} {interval(lead.ci[PRIMARY])}"
    seeds = f"seeds {r.seeds}"
    if len(r.encoders) == 1:
        return (f"{where}: only **{lead.encoder}** was grafted ({score}, {seeds}): nothing to "
                "rank it against.")
    nxt = r.encoders[1]
    tier = r.top_tier
    band = ("alone in its top tier" if len(tier) == 1 else
            f"top tier (near-tie band): {', '.join(tier)}")
    line = (f"{where}: **{lead.encoder}** leads ({score}; {band}); margin over the next, "
            f"{nxt.encoder}: {num(nxt.diff[PRIMARY], 3)} "
            f"{interval(nxt.diff_ci[PRIMARY], 3)} (paired, {CONFIDENCE:.0%}; {seeds}).")
    return line


def transfer_answers(ctx: ReportContext) -> list[str]:
    """Does the small backbone's winner sit in the large one's top tier? Only for suites where
    both backbones ran grafts; one backbone alone has no transfer to answer."""
    lines = []
    verdict = {True: "**is**", False: "**is not**", None: "cannot be placed"}
    for t in ctx.transfers:
        if not t.complete:
            continue
        tier = next(r.top_tier for r in ctx.rankings
                    if r.backbone == t.large and r.suite == t.suite)
        line = (f"Transfer on suite **{t.suite}**: the small-backbone winner (**{t.small_winner}** "
                f"on {t.small}) {verdict[t.small_winner_in_large_tier]} in the large backbone's "
                f"({t.large}) top tier ({', '.join(tier)}; Kendall tau-b "
                f"{num(t.agreement.get('tau_b'), 2)} over {len(t.encoders)} encoders; wrapper "
                f"delta {t.small} {ctx.wrapper_text(t.small, t.suite)}, {t.large} "
                f"{ctx.wrapper_text(t.large, t.suite)}).")
        blind_sides = [b for b in (t.small, t.large)
                       if (v := ctx.vision_of(b, t.suite)) is not None and v.flagged]
        if blind_sides:
            line += (f" **But the ranking on {' and '.join(blind_sides)} x {t.suite} "
                     f"measures nothing** (best graft not better than a no-vision control), "
                     f"so this transfer answer is not evidence either way.")
        lines.append(line)
    s = ctx.support
    if s["comparisons_total"] or s["seed_cells_total"]:
        lines.append(
            f"{s['comparisons_supporting']} of {s['comparisons_total']} backbone-suite "
            f"comparisons and {s['seed_cells_supporting']} of {s['seed_cells_total']} seed-level "
            f"cells support backbone-dependent rankings (rules under Rank transfer).")
    return lines


def _vision_answer(ctx: ReportContext) -> list[str]:
    flagged = [f"{v.backbone} x {v.suite} ({v.best_encoder} not better than "
               f"{', '.join(v.failed_controls)})" for v in ctx.vision if v.flagged]
    unchecked = [f"{v.backbone} x {v.suite}" for v in ctx.vision if not v.checked]
    lines = []
    if flagged:
        lines.append("**Encoder rankings that measure nothing** (best graft not better than a "
                     "no-vision control by a paired interval; see Vision use): "
                     + "; ".join(flagged) + ".")
    if unchecked:
        lines.append(f"Vision use not checked on {', '.join(unchecked)}: run the blind or "
                     "zero_image control.")
    return lines


def answer_lines(ctx: ReportContext) -> list[str]:
    """The short answer at the top, one paragraph each: per backbone x suite, then transfer."""
    if not ctx.records:
        return [f"No finished cells under `{ctx.results.root}` yet: nothing to answer."]
    if not ctx.rankings:
        kinds = Counter(r.kind for r in ctx.records)
        return ["No graft finished: no encoder ranking to answer (finished: "
                + ", ".join(f"{n} {kind}" for kind, n in sorted(kinds.items())) + ")."]
    lines = [ranking_answer(r, ctx) for r in ctx.rankings]
    return lines + transfer_answers(ctx) + _vision_answer(ctx)
