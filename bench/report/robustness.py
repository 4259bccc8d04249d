"""REPORT.md's "Robustness" section (the robustness tier): per backbone x suite, each encoder's
MSE under every perturbation and its degradation relative to clean with paired intervals, the
robustness ranking with its tie band (perturbed MSE first, the degradation ranked beside it),
whether the clean winner stays the winner per kind, a plot
of degradation against severity per encoder, and the transfer question. Left out of a report
whose results dir holds no robustness record (the tier is off by default)."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from bench.analysis.agreement import Interval
from bench.analysis.rankings import CONFIDENCE
from bench.analysis.robust_loop import (
    LoopRow, Rate, RobustOrder, closed_loop_rows, robust_orders,
)
from bench.analysis.robustness import RobustnessTable, robustness_all, robustness_transfer
from bench.report.closed_loop import stat_text
from bench.report.context import ReportContext
from bench.report.format import bullets, interval, num, pct, table, yes_no
from bench.results.robust import load_all_robust

PLOT_NAME = "robustness.png"
METHOD = (
    "Each trained cell's stored projector (native: the released policy as is) rescored, without "
    "retraining, on perturbed copies of every 4th held-out window (the same windows and the same "
    "perturbed frames for every cell of a suite: bench/robust/perturbations.py, drawn per window "
    "from a fixed seed). **Degradation** = (perturbed - clean) / clean normalised MSE on those "
    "windows, mean over releases and seeds; its "
    f"{CONFIDENCE:.0%} interval is the rankings' paired hierarchical bootstrap (releases, seeds "
    "within them, the held-out episodes the windows come from, then their windows, drawn once "
    "per replicate for every encoder; the clean level held fixed). Offline MSE under an "
    "image perturbation, not closed-loop success under a scene change.")


def robustness_section(ctx: ReportContext) -> str | None:
    robust, skipped = load_all_robust(ctx.results.root)
    if not robust:
        return None
    winners = {(r.backbone, r.suite): r.leader for r in ctx.rankings if r.leader}
    tables = robustness_all(ctx.records, robust, winners, n_resamples=ctx.n_resamples or 2000)
    parts = [METHOD]
    for t in tables:
        parts += [f"### {t.backbone} x {t.suite}", _table_text(t)]
    loop = _closed_loop_text(closed_loop_rows(ctx.records, robust))
    if loop is not None:
        parts += ["### In closed loop", loop,
                  _orders_text(robust_orders(ctx.records, robust,
                                             n_resamples=ctx.n_resamples or 1000))]
    parts.append("### Does the most robust encoder transfer across backbones?")
    parts.append(_transfer_text(robustness_transfer(tables)))
    plot = _plot(tables, ctx) if ctx.plots else None
    if plot is not None:
        parts.append(f"![degradation against severity]"
                     f"({plot.relative_to(ctx.out_path.parent).as_posix()})")
    if skipped:
        parts.append(bullets([f"skipped {f}: {why}" for f, why in skipped]))
    return "\n\n".join(parts)


def _table_text(t: RobustnessTable) -> str:
    if not t.rows:
        note = f" (stale, the cell was measured again: {', '.join(t.stale)})" if t.stale else ""
        return f"_No current robustness record{note}._"
    episodes = (f" from {t.n_episodes} held-out episodes" if t.n_episodes
                else " (no episode ids: drawn as independent units)")
    head = (f"{t.n_windows} windows{episodes}, releases {t.releases}, seeds {t.seeds}. Cell: "
            f"perturbed MSE, then degradation [{CONFIDENCE:.0%} CI].")
    rows = []
    for label in t.perturbations:
        cells = [t.cells.get((row, label)) for row in t.rows]
        rows.append([label, _params(t.params[label])] + [
            f"{num(c.mse, 3)}, {pct(c.relative)} [{pct(c.ci[0])}, {pct(c.ci[1])}]"
            if c is not None else "n/a" for c in cells])
    clean = [next((c.clean for (r, _), c in t.cells.items() if r == row), None)
             for row in t.rows]
    rows.insert(0, ["clean", ""] + [num(c, 3) for c in clean])
    parts = [head, table(rows, ["perturbation", "parameters"] + t.rows)]
    parts.append(_ranking_text(t))
    parts.append(_winner_text(t))
    if t.stale:
        parts.append(f"Stale robustness records left out (their cell was measured again; "
                     f"rerun their cases): {', '.join(t.stale)}.")
    return "\n\n".join(parts)


def _params(params: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in params.items())


def _ranking_text(t: RobustnessTable) -> str:
    if not t.ranking:
        return "_No robustness ranking: fewer than one graft with every perturbation._"
    degraded = {name: (i + 1, mean, ci, tier)
                for i, (name, mean, ci, tier) in enumerate(t.degradation_ranking)}
    rows = []
    for i, (name, mean, ci, tier) in enumerate(t.ranking):
        d_rank, d_mean, d_ci, d_tier = degraded.get(name, (None, None, (None, None), False))
        rows.append([i + 1, name, num(mean, 3), f"[{num(ci[0], 3)}, {num(ci[1], 3)}]",
                     yes_no(tier), "n/a" if d_mean is None else
                     f"{pct(d_mean)} [{pct(d_ci[0])}, {pct(d_ci[1])}]",
                     "n/a" if d_rank is None else f"{d_rank}{' (tie band)' if d_tier else ''}"])
    tie = [r[0] for r in t.ranking if r[3]]
    return ("Robustness ranking (grafts), led by what a user deploys: the **perturbed MSE**, mean "
            "over every perturbation above, lowest first; the tie band is the leader plus every "
            "graft whose paired difference to it has an interval containing 0. **"
            f"{t.most_robust}** predicts best under perturbation, tie band {tie}. The relative "
            "degradation (perturbed - clean) / clean is ranked beside it, not in its place: a "
            "graft with nothing to lose (`blind`) degrades least while predicting worst"
            f" (least degraded here: {t.least_degraded}).\n\n"
            + table(rows, ["rank", "encoder", "perturbed MSE", "CI", "tie band",
                           "degradation [CI]", "degradation rank"]))


def _winner_text(t: RobustnessTable) -> str:
    if t.clean_winner is None or not t.winners:
        return "_Clean winner: not known (no ranking of the grafts)._"
    rows = [[kind, ", ".join(f"{s}: {w}" for s, w in sorted(won.items())),
             yes_no(t.stays(kind))] for kind, won in t.winners.items()]
    return (f"Does the clean winner (**{t.clean_winner}**, lowest clean MSE on all held-out "
            "windows) stay the winner (lowest perturbed MSE) under each kind?\n\n"
            + table(rows, ["kind", "winner per severity", "clean winner stays"]))


def _closed_loop_text(rows: list[LoopRow]) -> str | None:
    """Success under each perturbation beside the clean success (Wilson 95%), per cell."""
    if not rows:
        return None
    labels = list(dict.fromkeys(label for r in rows for label in r.perturbed))
    body = [[f"{r.backbone} x {r.suite}", r.cell_id, _rate(r.clean)]
            + [f"{_rate(r.perturbed[label])}, -{r.lost[label]}/+{r.gained[label]}"
               if label in r.perturbed else "n/a" for label in labels] for r in rows]
    return ("Native and the best graft (lowest clean MSE) rolled out again with every rendered "
            "frame perturbed as offline (bench/robust/closed_loop.py): the same episodes (init "
            "states, env seeds) as the clean rollouts. Cell: successes/episodes, rate [Wilson "
            "95%], then -lost/+gained: episodes that succeeded clean and failed perturbed, and "
            "the reverse (paired by episode).\n\n"
            + table(body, ["backbone x suite", "cell", "clean"] + labels))


def _orders_text(orders: list[RobustOrder]) -> str:
    """Per perturbation: does the offline robustness ranking predict the closed-loop one?"""
    if not orders:
        return "_No perturbation rolled out on two paired items: no order to compare._"
    rows = []
    for o in orders:
        tau = ("n/a" if o.tau_b is None else
               f"{stat_text(o.tau_b)} " + (interval((o.interval.low, o.interval.high), 2)
                                           if isinstance(o.interval, Interval)
                                           else f"({o.interval})"))
        for k, item in enumerate(o.items):
            rows.append([f"{o.backbone} x {o.suite}", o.label, item,
                         ", ".join(map(str, o.seeds[item])),
                         f"{num(o.clean_mse[k])} -> {num(o.mse[k])} "
                         f"(x{o.mse[k] / o.clean_mse[k]:.2f})",
                         f"{o.clean_success[k]:.0%} -> {o.success[k]:.0%}", o.episodes[k],
                         tau if k == 0 else ""])
        if o.missing:
            rows.append([f"{o.backbone} x {o.suite}", o.label, f"_{o.missing}_", "", "", "",
                         "", ""])
    return ("Does the offline robustness ranking predict the closed-loop one? Per perturbation, "
            "the rolled-out items' offline MSE on the robustness windows (clean -> perturbed) "
            "and their success (clean -> perturbed, the same episodes), means over seeds; "
            "Kendall tau-b of -perturbed MSE against perturbed success over the items, with "
            "the closed loop's paired bootstrap interval (each item's seeds, then windows and "
            "episodes drawn). With two items tau-b is +1 (same order) or -1; its interval says "
            "whether that order survives the draws.\n\n"
            + table(rows, ["backbone x suite", "perturbation", "item", "seeds",
                           "offline MSE (clean -> perturbed)", "success", "episodes",
                           "tau-b [95% CI]"]))


def _rate(rate: Rate | None) -> str:
    if rate is None:
        return "n/a (no clean rollouts in the record)"
    lo, hi = rate.ci
    return f"{rate.successes}/{rate.episodes} = {rate.rate:.0%} [{lo:.0%}, {hi:.0%}]"


def _transfer_text(transfers: list[dict]) -> str:
    if not transfers:
        return ("_Not measured: it needs robustness rankings of two backbones on one suite._")
    lines = []
    for x in transfers:
        tau = x["agreement"].get("tau_b")
        lines.append(
            f"{x['suite']}: most robust on {x['small']} **{x['small_most_robust']}**, on "
            f"{x['large']} **{x['large_most_robust']}** ("
            + ("the same" if x["same"] else "different; " + (
                "inside" if x["small_most_robust"] in x["large_tie_band"] else "outside")
               + f" {x['large']}'s tie band {x['large_tie_band']}")
            + f"); Kendall tau-b of the robustness scores over {len(x['encoders'])} encoders: "
              f"{num(tau, 2)}")
    return bullets(lines)


def _plot(tables: list[RobustnessTable], ctx: ReportContext) -> Path | None:
    """Degradation against severity, one panel per backbone x suite and kind, a line per row."""
    panels = [(t, kind) for t in tables if t.rows
              for kind in dict.fromkeys(p.split(":")[0] for p in t.perturbations)]
    if not panels:
        return None
    cols = min(len(panels), 4)
    rows = -(-len(panels) // cols)
    fig = Figure(figsize=(3.2 * cols, 2.8 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax in axes[len(panels):]:
        ax.set_visible(False)
    # One colour per row in every panel, from 20 (the default cycle's 10 repeat past 10 rows).
    palette = matplotlib.colormaps["tab20"]
    rows_seen = list(dict.fromkeys(row for t in tables for row in t.rows))
    colour = {row: palette(i % 20) for i, row in enumerate(rows_seen)}
    for ax, (t, kind) in zip(axes, panels):
        labels = [p for p in t.perturbations if p.startswith(kind + ":")]
        for row in t.rows:
            points = [(int(p.split(":")[1]), t.cells[(row, p)]) for p in labels
                      if (row, p) in t.cells]
            if points:  # severity 0 is the clean image: no degradation by definition
                ax.plot([0] + [s for s, _ in points], [0.0] + [100 * c.relative
                                                              for _, c in points],
                        marker="o", label=row, color=colour[row])
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_xticks(range(4))
        ax.set_title(f"{t.backbone} x {t.suite}: {kind}", fontsize=8)
        ax.set_xlabel("severity", fontsize=7)
        ax.set_ylabel("degradation (%)", fontsize=7)
        ax.legend(fontsize=6)
    folder = ctx.out_path.parent / f"{ctx.out_path.stem}_plots"
    folder.mkdir(parents=True, exist_ok=True)
    fig.savefig(folder / PLOT_NAME, dpi=100)
    return folder / PLOT_NAME
