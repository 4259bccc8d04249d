"""The closed-loop section of REPORT.md and the agreement clause its first caveat quotes."""

from __future__ import annotations

from bench.analysis.agreement import SPEARMAN_TIES, TIE_RULE, Interval, Undefined
from bench.analysis.offline_measures import MEASURES, TABLE_STATISTICS, VERDICT_STATISTIC
from bench.analysis.rankings import CONFIDENCE
from bench.report.context import ReportContext
from bench.report.format import cells_by, interval, num, table

CLOSED_LOOP_INTRO = (
    "Cells run with `--rollouts N` are also rolled out in the LIBERO simulator from fixed init "
    "states, identical for every cell (paired). Success is per episode; its interval is Wilson's "
    f"({CONFIDENCE:.0%}). Agreement (bench.analysis.agreement, one tie rule, below) compares the "
    "offline ranking (predicted: -MSE) with the closed-loop ranking (actual: success rate) of "
    "the rolled-out items (means over seeds): Kendall tau-b and top-weighted tau (+1 = same "
    "order), MMRV (SimplerEnv's mean maximum rank violation, in success-rate units, 0 = no "
    "violation), Pearson r of -MSE and success (+1 = lower MSE goes with higher success) and "
    "top-1 regret (success lost by taking the offline winner). Intervals: a paired bootstrap "
    "that draws each item's training seeds (as many as it has, with replacement: both its "
    "offline score and its success carry the training's variance), then held-out episodes "
    "within their tasks and windows within a drawn episode, and rollout episodes within their "
    "task, n - 1 of n at each level, each once for all items. A closed-loop "
    "ranking that is one tie has no order: its statistics are undefined, never 0. Offline MSE is "
    "not closed-loop success; with few items and few episodes per task the interval is wide, "
    "and a tau from 3 items or a success rate from 10 episodes decides little."
)
AGREEMENT_ROWS = (("tau_b", "Kendall tau-b"), ("weighted_tau", "weighted tau"),
                  ("mmrv", "MMRV"), ("pearson_r", "Pearson r (-MSE, success)"),
                  ("top1_regret", "top-1 regret"))


def stat_text(value, digits: int = 2) -> str:
    """A statistic from bench.analysis.agreement: its number, or 'undefined (reason)'."""
    return str(value) if isinstance(value, Undefined) else num(value, digits)


def agreement_summary(cl) -> str:
    """One clause for the caveat: the measured agreement of one backbone x suite, or why none."""
    where = f"{cl.backbone} x {cl.suite}"
    if not cl.measured:
        return f"{where}: no agreement measured ({cl.missing})"
    tau = cl.agreement["tau_b"]
    if isinstance(tau, Undefined):
        return f"{where}: Kendall tau-b {tau} over {len(cl.items)} items"
    shown = [f"{label.split(' (')[0]} {stat_text(cl.agreement[k])} "
             f"{interval(cl.interval_of(k), 2)}" for k, label in AGREEMENT_ROWS[:4]]
    return (f"{where}: {candidate_clause(cl)}over all {len(cl.items)} items " + ", ".join(shown)
            + ". " + measure_verdict(cl).rstrip("."))


def candidate_clause(cl) -> str:
    """'on the k candidates Kendall tau-b x [lo, hi]; ' (the question a team asks), or ''."""
    if "tau_b" not in cl.candidate_agreement:
        return ""
    if isinstance(cl.candidate_agreement["tau_b"], Undefined):
        return f"on the candidates no agreement ({cl.candidate_agreement['tau_b'].reason}); "
    return (f"on the {len(cl.candidates)} candidates ({', '.join(cl.candidates)}) Kendall tau-b "
            f"{stat_text(cl.candidate_agreement['tau_b'])} "
            f"{interval(cl.candidate_interval_of('tau_b'), 2)}; ")


def _versus(m) -> str:
    """A measure's tau-b minus the full chunk's, with its paired interval."""
    if isinstance(m.versus_full, Undefined) or m.versus_full is None:
        return f"not paired ({m.versus_full.reason})" if m.versus_full else "n/a"
    ci = m.versus_full_interval
    return (f"{m.versus_full:+.2f} "
            + (interval((ci.low, ci.high), 2) if isinstance(ci, Interval) else f"({ci})"))


def measure_verdict(cl) -> str:
    """Which offline measure to read on this backbone x suite, from the measurement: a measure
    replaces the full-chunk MSE only where its Kendall tau-b with success is above the full
    chunk's by a paired interval that excludes 0 (both on one draw of seeds, windows and
    episodes); otherwise the full chunk (the offline score every cell reports) stands."""
    full = next((m for m in cl.measures if m.name == MEASURES[0].name), None)
    if full is None or full.missing:
        return "No offline measure was compared (the full chunk's inputs are missing)."
    better = [m for m in cl.measures if isinstance(m.versus_full_interval, Interval)
              and m.versus_full_interval.low > 0]
    pick = max(better, key=lambda m: m.value[VERDICT_STATISTIC], default=full)
    tau = (f"Kendall tau-b {stat_text(pick.value[VERDICT_STATISTIC])} "
           f"{interval(pick.interval_of(VERDICT_STATISTIC), 2)}")
    others = "; ".join(f"{m.name} {_versus(m)}" for m in cl.measures
                       if m is not full and m is not pick and not m.missing)
    if pick is full:
        head = (f"Which offline measure to read: the **{full.name}** MSE (the offline score), "
                f"{tau}; no other measure agreed measurably better (tau-b minus the full "
                f"chunk's, paired: {others or 'none measured'})")
    else:
        head = (f"Which offline measure to read: the **{pick.name}** MSE, {tau}, above the full "
                f"chunk's by {_versus(pick)}" + (f" (others: {others})" if others else ""))
    low = pick.interval_of(VERDICT_STATISTIC)
    if low is not None and low[0] <= 0:
        head += "; even it is not measured to agree (its interval reaches 0)"
    return head + "."


def closed_loop_caveat(ctx: ReportContext) -> str:
    """The report's first caveat: offline MSE is not success, and how far they agreed here."""
    rolled = sum(1 for cl in ctx.closed_loop for n in cl.n_episodes if n)
    return ("**Offline action MSE is not closed-loop task success.** "
            + (f"Rollouts in the LIBERO simulator were run for {rolled} rolled-out item(s); the "
               "offline ranking against the closed-loop one, measured ('Closed loop'): "
               + "; ".join(agreement_summary(cl) for cl in ctx.closed_loop)
               + ". Elsewhere this is " if rolled else "No simulator rollouts were run, so their "
               "agreement with the offline ranking is not measured here; this is ")
            + "a pre-commitment diagnostic for choosing an encoder, not a deployment claim.")


def rollout_hardware(records) -> dict[str, list[str]]:
    """{hardware line: cell ids} of the records holding episodes, when they name more than one
    (a closed-loop study continued on another CPU, kernel set or thread count); {} otherwise."""
    found: dict[str, list[str]] = {}
    for r in records:
        if (r.run.rollouts or {}).get("episodes"):
            found.setdefault(str(r.run.hardware), []).append(r.cell_id)
    return found if len(found) > 1 else {}


def hardware_caveat(found: dict[str, list[str]]) -> str:
    """The caveat naming each machine the episodes were rolled out on, and what that moves."""
    # The figures: studies/sim/REBUILD.md, "A graft on other kernels".
    return (f"**Rollouts ran on {len(found)} machines' kernels** ({cells_by(found)}). Episodes "
            "do not rebuild across kernels: one pinned Lite0 graft rolled out under AVX2 instead "
            "of AVX-512 kernels changed 12 of its 40 episodes' outcomes (28 -> 26 successes); "
            "retrained on them, its offline MSE moved by 2.5e-7 relative (studies/sim/REBUILD.md). "
            "Compare these items' success by its intervals, never episode by episode.")


MEASURE_COLUMNS = {"tau_b": "Kendall tau-b", "spearman_rho": "Spearman", "pearson_r": "Pearson r",
                   "mmrv": "MMRV", "top1_regret": "top-1 regret"}
MEASURES_INTRO = (
    "Offline measures against success (bench.analysis.offline_measures; predicted: -measure, "
    "actual: success rate; each statistic with its bootstrap interval, windows and episodes "
    "drawn as above; 'per task' ranks item x task pairs, each pair's windows and episodes "
    "only). A measure whose inputs the records lack is 'not measured', never 0. "
    + SPEARMAN_TIES + " Definitions: "
    + "; ".join(f"**{m.name}**: {m.definition}" for m in MEASURES) + "."
)


def measures_table(cl) -> str:
    """One table: a row per offline measure, its agreement statistics with their intervals."""
    rows = []
    for m in cl.measures:
        if m.missing:
            rows.append([m.name, "not measured", *[""] * (len(TABLE_STATISTICS) + 2), m.missing])
            continue
        cells = [stat_text(m.value[k]) + " " + (interval(m.interval_of(k), 2)
                                                if m.interval_of(k) else
                                                f"({stat_text(m.intervals.get(k))})")
                 for k in TABLE_STATISTICS]
        rows.append([m.name, len(m.labels), *cells,
                     "" if m.versus_full is None else _versus(m), _on_candidates(m), m.note])
    return table(rows, ["measure", "rows", *(MEASURE_COLUMNS[k] for k in TABLE_STATISTICS),
                        "tau-b minus the full chunk's (paired)", "tau-b on the candidates",
                        "note"])


def _on_candidates(m) -> str:
    """A measure's Kendall tau-b over the candidate items' rows, with its interval."""
    c = m.on_candidates
    if c is None:
        return "n/a"
    if c.missing:
        return f"not measured ({c.missing})"
    return (f"{stat_text(c.value[VERDICT_STATISTIC])} "
            f"{interval(c.interval_of(VERDICT_STATISTIC), 2)} ({len(c.labels)} rows)")


def _stat_cells(value, ci, n_resamples: int) -> list[str]:
    kept = f"{ci.replicates} of {n_resamples}" if isinstance(ci, Interval) else "0"
    shown = (interval((ci.low, ci.high), 2) if isinstance(ci, Interval)
             else stat_text(ci) if ci is not None else "n/a")
    return [stat_text(value) if value is not None else "n/a", shown, kept]


def agreement_table(cl) -> str:
    """The agreement over every rolled-out item, and beside it over the candidates alone."""
    with_candidates = bool(cl.candidate_agreement)
    rows = []
    for key, label in AGREEMENT_ROWS:
        row = [label, *_stat_cells(cl.agreement[key], cl.intervals.get(key), cl.n_resamples)]
        if with_candidates:
            row += _stat_cells(cl.candidate_agreement.get(key), cl.candidate_intervals.get(key),
                               cl.n_resamples)
        rows.append(row)
    ci = f"{CONFIDENCE:.0%} bootstrap CI"
    headers = ["statistic", f"all {len(cl.items)} items", ci, "replicates defined"]
    if with_candidates:
        own = cl.candidate_episodes and cl.candidate_episodes != cl.common_episodes
        headers += [f"the {len(cl.candidates)} candidates"
                    + (f" ({cl.candidate_episodes} episodes)" if own else ""), ci,
                    "replicates defined"]
    text = (f"Agreement (Kendall p over all items = {stat_text(cl.agreement['p_value'], 3)}; "
            "candidates: the native policy and grafts of encoders with trained weights, "
            "bench.analysis.candidates"
            + (f": {', '.join(cl.candidates) or 'none'}" if with_candidates else "") + "):")
    return text + "\n\n" + table(rows, headers)


def closed_loop_section(ctx: ReportContext) -> str:
    if not ctx.closed_loop:
        return ("_No cell was rolled out (run with `--rollouts N` on a simulated suite, see "
                "docs/CLOSED_LOOP.md)._")
    parts = [CLOSED_LOOP_INTRO, "Tie rule (here the cheaper tier is offline -MSE and the graft "
             f"score is closed-loop success): {TIE_RULE}"]
    if any(cl.measures for cl in ctx.closed_loop):
        parts.append(MEASURES_INTRO)
    for cl in ctx.closed_loop:
        head = f"**{cl.backbone} x {cl.suite}**"
        rows = [[item, ", ".join(map(str, cl.seeds.get(item, []))), num(mse), f"{succ:.1%}",
                 interval(ci, 2), n]
                for item, mse, succ, ci, n in zip(cl.items, cl.mse, cl.success, cl.success_ci,
                                                  cl.n_episodes)]
        if rows:
            head += "\n\n" + table(rows, ["item", "seeds", "norm. MSE", "success",
                                          f"success {CONFIDENCE:.0%} CI", "episodes"])
        if cl.uncommon_episodes:
            head += (f"\n\nPaired on the episodes (task, init state) every rolled-out cell ran: "
                     f"{cl.uncommon_episodes} episode(s) that only some cells ran are left out "
                     f"here ({cl.common_episodes} per cell; a sequential study's later rounds run "
                     "the items still open)"
                     + (f"; the candidates' agreement is on the {cl.candidate_episodes} episodes "
                        "every candidate ran" if cl.candidate_episodes > cl.common_episodes
                        else "")
                     + ". The working group's verdict below compares each pair on all the "
                     "episodes both ran.")
        if not cl.measured:
            head += f"\n\n_No agreement: {cl.missing}._"
        else:
            head += "\n\n" + agreement_table(cl)
            if cl.measures:
                head += (f"\n\nOffline measures against success:\n\n{measures_table(cl)}"
                         f"\n\n{measure_verdict(cl)}")
        parts.append(head)
    return "\n\n".join(parts)
