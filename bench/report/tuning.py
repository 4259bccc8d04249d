"""REPORT.md's tuned-encoder section: tuned minus frozen per encoder, with paired intervals and
the cost per step, and whether the encoder ranking changes when every encoder is tuned."""

from __future__ import annotations

from bench.analysis.rankings import CONFIDENCE
from bench.analysis.tuning import FLAT_TOLERANCE, TunedStudy, tuned_vs_frozen
from bench.report.context import ReportContext
from bench.report.format import bullets, interval, is_num, num, pct, table

TITLE = "Tuned encoder vs frozen"
RULE = (
    "A tuned cell trains the projector AND the encoder's weights (at the protocol's "
    "`encoder_lr`, same steps and schedule; backbone frozen; normalisation statistics and "
    "dropout in eval mode), its encoder run in the loop; its frozen twin is the cell of the same "
    "encoder and seed that trained the projector alone for as many steps, on stored features "
    "(the graft; for `tuned_encoder_1_8`, the short_1_8 graft). tuned - frozen is normalised "
    "MSE averaged over the (release, seed) cells both have (negative: tuning helps); the interval "
    "is the rankings' paired hierarchical bootstrap (releases, seeds, held-out episodes, "
    "windows). Verdict (only with at least two seeds, never from one, and only where the frozen "
    "twin's loss had flattened): tuning helps / hurts when the interval lies below / above 0. "
    f"Flattened: the mean logged loss of the frozen twins' last quarter of steps lies within "
    f"{FLAT_TOLERANCE:.0%} below the quarter before (column 'frozen loss, last quarter'). "
    "s/step: the records' train phase (with its before/after probe loss) per optimiser step, on "
    "the machine and load the records name; the frozen graft's leaves out its one-off feature "
    "extraction."
)
SPLIT_RULE = (
    "Split by the zero-learning-rate twin (`tuned_encoder_lr0`: the tuned cell's live, "
    "full-precision feature path with the encoder held, no gradient through it), on the cells "
    "all three have: twin - frozen is what the live path does against the stored fp16 features; "
    "tuned - twin is what moving the encoder does (its weights, and its gradients in the clip the "
    "projector shares). The two add up to tuned - frozen; both intervals come from the same "
    "replicates."
)


def _ratio(tuned: float, frozen: float) -> str:
    return f"x{num(tuned / frozen, 3)}" if is_num(tuned) and is_num(frozen) and frozen > 0 else "n/a"


def _at(steps) -> str:
    return f" at {steps} steps" if steps else ""


def tuning_section(ctx: ReportContext, study: TunedStudy | None = None) -> str | None:
    """None (the section is left out) when no record is of a tuned-encoder kind."""
    study = study or tuned_vs_frozen(ctx.records, n_resamples=ctx.n_resamples or 2000)
    if not study.comparisons and not study.notes:
        return None
    rows = [[c.backbone, c.suite, c.encoder, str(c.steps), ", ".join(map(str, c.seeds)),
             pct(c.frozen_flat), num(c.frozen_mse), num(c.tuned_mse), num(c.diff, 3),
             interval(c.diff_ci, 3), pct(c.relative), c.verdict,
             f"{num(c.tuned_step_s, 3)} vs {num(c.frozen_step_s, 3)} "
             f"({_ratio(c.tuned_step_s, c.frozen_step_s)})"]
            for c in study.comparisons]
    parts = [RULE]
    if rows:
        parts.append(table(rows, ["backbone", "suite", "encoder", "steps", "seeds",
                                  "frozen loss, last quarter", "frozen norm. MSE",
                                  "tuned norm. MSE", "tuned - frozen", f"{CONFIDENCE:.0%} CI",
                                  "relative", "verdict", "s/step tuned vs frozen"]))
    splits = [[c.backbone, c.suite, c.encoder, str(c.steps), ", ".join(map(str, s.seeds)),
               num(s.twin_mse), num(s.path, 3), interval(s.path_ci, 3), s.path_verdict,
               num(s.moved, 3), interval(s.moved_ci, 3), s.moved_verdict, num(s.twin_step_s, 3)]
              for c in study.comparisons if (s := c.twin) is not None]
    if splits:
        parts += [SPLIT_RULE, table(splits, [
            "backbone", "suite", "encoder", "steps", "seeds", "twin norm. MSE", "twin - frozen",
            f"{CONFIDENCE:.0%} CI", "live path", "tuned - twin", f"{CONFIDENCE:.0%} CI",
            "encoder's move", "s/step twin"])]
    lines = []
    for r in study.rankings:
        if len(r.frozen_order) < 2:
            lines.append(f"{r.backbone} x {r.suite}{_at(r.steps)}: one encoder compared "
                         f"({r.frozen_order[0]}): no ranking to change")
            continue
        change = ("**the ranking changes**" + (f", the leader too ({r.frozen_order[0]} -> "
                                               f"{r.tuned_order[0]})" if r.leader_changed else "")
                  if r.changed else "the ranking is unchanged")
        lines.append(f"{r.backbone} x {r.suite}{_at(r.steps)}: frozen "
                     f"{' > '.join(r.frozen_order)}; tuned "
                     f"{' > '.join(r.tuned_order)} ({change}; point means over each encoder's "
                     "paired seeds, not a test)")
    lines += study.notes
    if lines:
        parts.append(bullets(lines))
    return "\n\n".join(parts)
