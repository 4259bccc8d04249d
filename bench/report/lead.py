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
    seeds = (f"seeds {r.seeds}" if len(r.releases) == 1 else
             f"releases {r.releases} x seeds {r.seeds}")
    if r.n_episodes:
        unit = "windows (no episode ids)" if r.episodes_from == "none" else "episodes"
        seeds += f", {r.n_episodes} held-out {unit}; drawn: " + ", ".join(
            level for level, n in (("releases", len(r.releases)), ("seeds", len(r.seeds)),
                                   (unit.split()[0], r.n_episodes)) if n > 1)
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


def _transfer_tau(t) -> str:
    """The transfer's tau-b on the candidates first (the question a team asks), then on all."""
    every = f"{num(t.agreement.get('tau_b'), 2)} over all {len(t.encoders)} encoders"
    if not t.candidate_agreement:
        return every
    return (f"{num(t.candidate_agreement.get('tau_b'), 2)} over the {len(t.candidates)} "
            f"candidates, {every}")


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
                f"({t.large}) top tier ({', '.join(tier)}; Kendall tau-b {_transfer_tau(t)}; "
                f"wrapper delta {t.small} {ctx.wrapper_text(t.small, t.suite)}, {t.large} "
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


def screen_answers(ctx: ReportContext) -> list[str]:
    """Per backbone x suite: how the cheap tiers order the candidates, and which of them the
    screen recommends (beats the best naive baseline by a paired interval above 0)."""
    from bench.analysis.tiers import ALL, CANDIDATES
    from bench.report.screen import naive_text

    lines = []
    for b, s in sorted({(a.backbone, a.suite) for a in ctx.screen_agreements}):
        rows = {(a.item_set, a.tier): a for a in ctx.screen_agreements
                if (a.backbone, a.suite) == (b, s) and a.point is not None}
        mine = [a for (item_set, _), a in rows.items() if item_set == CANDIDATES]
        if not mine:
            continue
        taus = []
        for a in mine:
            every = rows.get((ALL, a.tier))
            taus.append(f"{a.tier} {num(a.point.tau_b, 2)}"
                        + (f" ({num(every.point.tau_b, 2)})" if every else ""))
        good = [f"{a.tier} ({naive_text(a)})" for a in mine if a.recommended]
        verdict = (f"the screen recommends {'; '.join(good)}" if good else
                   "no proxy or short graft beats the best naive baseline by a paired interval "
                   "above 0, so the screen recommends none")
        lines.append(f"Screen on **{b} x {s}**, Kendall tau-b with the graft on the "
                     f"{len(mine[0].encoders)} candidates (over all items in brackets): "
                     + ", ".join(taus) + f"; {verdict} (Screening many encoders).")
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
    return lines + transfer_answers(ctx) + screen_answers(ctx) + _vision_answer(ctx)
