"""The analysis sections of REPORT.md: each takes a ReportContext and returns markdown.

Every section renders what the stored records allow and says what is missing instead of failing.
Provenance and per-task sections live in report_provenance.py.
"""

from __future__ import annotations

from bench.analysis.rankings import CONFIDENCE, PRIMARY
from bench.analysis.controls import UNCHECKED_HINT, VISION_RULE, VisionCheck, VisionComparison
from bench.analysis.transfer import SUPPORT_RULES, min_exact_kendall_p
from bench.grid.kinds import get_kind
from bench.report.closed_loop import closed_loop_caveat, hardware_caveat, rollout_hardware
from bench.report.context import ReportContext
from bench.report.encoders import encoder_infos, encoders_caveat, encoders_table
from bench.report.screen import SCATTER_TITLE
from bench.report.format import (bullets, cells_by, half_width, interval, num, pct, table,
                               yes_no)
from bench.report.study import DISAGREES, compare_records
from bench.results.record import RAW

TIER_RULE = (
    f"**Top tier (near-tie band)**: the leader (lowest mean normalised MSE over releases and "
    f"seeds) plus every encoder whose paired difference to the leader (encoder minus leader, "
    f"same releases, seeds, episodes and windows) has a {CONFIDENCE:.0%} interval that contains 0."
)
INTERVAL_METHOD = (
    "Intervals: a paired hierarchical bootstrap (bench/analysis/hierarchy.py) that draws "
    "releases, seeds within a release, held-out episodes, then windows within each episode, "
    "n - 1 of n units at each level (Rao and Wu's rescaling), one draw for every cell of the "
    "backbone x suite so differences are paired; percentile intervals widened by t / z on the "
    "Satterthwaite degrees of freedom of the levels' mean squares (few releases or seeds: wider). "
    "Each backbone x suite below names the levels its intervals drew."
)


def cell_label(key) -> str:
    """A ranking's per-cell key as printed: 's0' for a seed, 'rel1-seed0' as it is."""
    return f"s{key}" if isinstance(key, int) else str(key)


def _gap(c: VisionComparison) -> str:
    return (f"{c.control}: control - graft {num(c.diff, 3)}, {CONFIDENCE:.0%} CI "
            f"{interval(c.diff_ci, 3)}, seeds {c.seeds}")


def vision_text(check: VisionCheck | None) -> str:
    """One sentence: does this backbone x suite's ranking measure vision at all?"""
    if check is None or not check.checked:
        notes = f" ({'; '.join(check.notes)})" if check is not None and check.notes else ""
        return f"{UNCHECKED_HINT[0].upper()}{UNCHECKED_HINT[1:]}{notes}."
    if check.flagged:
        failed = [c for c in check.comparisons if not c.better]
        return (f"Vision use: **this encoder ranking says nothing**: the best graft "
                f"(**{check.best_encoder}**) is not better than "
                f"{'; '.join(_gap(c) for c in failed)}. The backbone may ignore its images here, "
                f"so the order of the encoders is noise.")
    return (f"Vision use: the best graft (**{check.best_encoder}**) beats every no-vision "
            f"control present ({'; '.join(_gap(c) for c in check.comparisons)}).")


def caveats(ctx: ReportContext) -> str:
    profiles = sorted({r.measured.profile for r in ctx.records if r.measured.profile}
                      | ({ctx.results.grid_profile} if ctx.results.grid_profile else set()))
    hashes = sorted({r.measured.protocol_hash for r in ctx.records if r.measured.protocol_hash})
    protocol = (ctx.records[0].measured.protocol or {}) if ctx.records else {}
    if all(k in protocol for k in ("split_seed", "heldout_episodes_per_task", "eval_noise_seed")):
        split = (f" (split_seed={protocol['split_seed']}, "
                 f"{protocol['heldout_episodes_per_task']} episodes per task)")
        crn = f", eval_noise_seed={protocol['eval_noise_seed']}"
    else:  # no finished record carries the protocol: leave its values out, say why
        split, crn = " (its seed and size are left out: no finished cell records them)", ""
    wrapper = [f"{b} x {s}: {ctx.wrapper_text(b, s)}" for b, s in sorted(ctx.wrapper)]
    lines = [
        closed_loop_caveat(ctx),
        "**Conclusions are conditional on the fixed wrapper** (adaptive average pool to the "
        "native token grid, LayerNorm without affine, one trainable Linear). Its neutrality "
        "delta (native-wrapped vs native) is shown beside every ranking: "
        + ("; ".join(wrapper) if wrapper else "not measured in these results") + ".",
        f"**Profile(s) that ran: {', '.join(profiles) or 'unknown'}.**"
        + (" The tiny profile's policies and suites are tiny and generated: its numbers exercise "
           "the code paths and say **nothing** about real VLAs, whatever the encoder."
           if any(p.startswith("tiny") for p in profiles) else ""),
        "**What offline action MSE means here**: held-out whole EPISODES per task, split with a "
        f"fixed split seed{split} that does not "
        "depend on the cell seed, so every cell of a suite is scored on identical windows; the "
        "backbone's own flow-matching sampler (its default denoising steps) with noise fixed per "
        f"window (common random numbers{crn}); "
        "only the real action dimensions (LIBERO: 7; padding masked out); over the full action "
        "chunk; reported in the backbone's normalised action space (primary) and in raw units.",
        "**Two machines differ on the same cell** as far as the release differs: with the tiny "
        "releases retrained on each, by up to 2.3% MSE on the CI slice (docs/CI.md) and 7.6% on "
        "a 10,000-step graft (studies/sim/REBUILD.md); with the release pinned by content hash, "
        "by 2.5e-7 relative (a 10,000-step graft, AVX512 against AVX2 kernels). `hardware` in "
        "each record names the CPU and its kernels: between two machines' reports, compare on "
        "pinned releases.",
        "**MSE levels are not comparable across backbones** (different action normalisation): "
        "compare rankings across backbones, never levels; every plot gives each backbone its "
        "own axis.",
    ]
    encoders = encoders_caveat(encoder_infos(ctx.records))
    if encoders is not None:  # beside the profile line: what the encoders' numbers can say
        lines.insert(3, encoders)
    flagged = [f"{v.backbone} x {v.suite}" for v in ctx.vision if v.flagged]
    unchecked = [f"{v.backbone} x {v.suite}" for v in ctx.vision if not v.checked]
    if flagged or unchecked:
        lines.append(
            "**A ranking only means something if the policy uses its images.** "
            + (f"Flagged (best graft not better than its blind / zero-image control): "
               f"{', '.join(flagged)}. " if flagged else "")
            + (f"Vision use not checked (no blind or zero_image control): "
               f"{', '.join(unchecked)}." if unchecked else ""))
    differ = sorted({r.constant for rows in compare_records(ctx.records).values() for r in rows
                     if r.status == DISAGREES})
    if differ:
        lines.append(f"**Constants that differ from the published study's**: {', '.join(differ)} "
                     "(table 'Protocol constants: the study's and ours' under Provenance).")
    return bullets(lines + mixed_warnings(ctx.records, hashes))


def mixed_warnings(records, hashes: list[str]) -> list[str]:
    """What a folder mixes: protocols, a backbone's releases, the machines episodes ran on."""
    out = []
    if len(hashes) > 1:
        out.append(f"**Warning: records come from {len(hashes)} different protocols** "
                   f"({', '.join(hashes)}); numbers measured under different rules are mixed.")
    out += [release_warning(b, cells) for b, cells in mixed_releases(records).items()]
    machines = rollout_hardware(records)
    if machines:
        out.append(hardware_caveat(machines))
    return out


def mixed_releases(records) -> dict[str, dict[str, list[str]]]:
    """{backbone: {revision: cell ids}} for each backbone release (release 0: the backbone's
    name; release r: 'backbone release r') whose records were measured on more than one set of
    weights (sha256 or hub commit): a study continued on another machine. Releases measured on
    purpose (Profile.releases_per_backbone) are each their own and never flagged."""
    found: dict[str, dict[str, list[str]]] = {}
    for r in records:
        name = r.backbone if not r.release else f"{r.backbone} release {r.release}"
        found.setdefault(name, {}).setdefault(str(r.measured.revision), []).append(r.cell_id)
    return {b: revs for b, revs in sorted(found.items()) if len(revs) > 1}


def release_warning(backbone: str, cells: dict[str, list[str]]) -> str:
    """The caveat naming each release of `backbone` and the cells measured on it."""
    return (f"**Warning: {backbone}'s records were measured on {len(cells)} different releases** "
            f"({cells_by(cells)}); their numbers are not comparable: measure them again on one "
            "release, or pin it in the grid file's [releases] (studies/sim/REBUILD.md).")


def rankings_section(ctx: ReportContext) -> str:
    if not ctx.rankings:
        return "No graft cells in the results: nothing to rank."
    parts = [f"Ranked by mean normalised MSE over releases and seeds (lower is better); raw MSE "
             f"beside it. "
             f"{INTERVAL_METHOD} {ctx.n_resamples} replicates. Differences in raw units are "
             f"against the normalised leader. {TIER_RULE}",
             "The encoders ranked: where each comes from, its weights (the records' "
             "`encoder_weights`) and the side its input was resized to:",
             encoders_table(encoder_infos(ctx.records))]
    for r in ctx.rankings:
        parts.append(f"### {r.backbone} x {r.suite}")
        parts.append(f"Wrapper neutrality delta on {r.backbone} x {r.suite}: "
                     f"{ctx.wrapper_text(r.backbone, r.suite)}.")
        parts.append(vision_text(ctx.vision_of(r.backbone, r.suite)))
        if r.error:
            parts.append(f"_Not ranked: {r.error}_")
            continue
        rows = []
        for e in r.encoders:
            seeds = ", ".join(f"{cell_label(s)}: {num(v)}" for s, v in e.per_seed[PRIMARY].items())
            rows.append([e.rank, e.encoder, num(e.mean[PRIMARY]), half_width(e.ci[PRIMARY]),
                         interval(e.ci[PRIMARY]), num(e.mean[RAW]), interval(e.ci[RAW]),
                         seeds, num(e.diff[PRIMARY], 3), interval(e.diff_ci[PRIMARY], 3),
                         yes_no(e.in_top_tier)])
        parts.append(table(rows, ["rank", "encoder", "norm. MSE", "±", "95% CI", "raw MSE",
                                  "raw 95% CI", "per cell (norm.)", "Δ vs leader",
                                  "Δ 95% CI", "top tier"]))
        parts.append(f"{r.n_windows} held-out windows from {r.n_episodes} episodes; releases "
                     f"{r.releases}; seeds {r.seeds}; intervals: {r.interval}. Per-cell winners: "
                     + ", ".join(f"{cell_label(s)}: {w}" for s, w in r.seed_winners.items())
                     + (" (**seed-sensitive**)" if r.seed_sensitive else "") + ".")
    return "\n\n".join(parts)


CANDIDATES_TEXT = (
    "**On the candidates** a team would choose between (encoders whose registry entry runs "
    "trained weights in this world, bench.analysis.candidates; no random twin, known-answer "
    "encoder or random-init stand-in), the same statistics, beside those over every encoder:")


def candidate_transfer_table(ctx: ReportContext) -> str | None:
    """The transfer's agreement over the candidates beside over all items; None without any."""
    rows = []
    for t in ctx.transfers:
        if not t.complete or not t.candidate_agreement:
            continue
        a = t.candidate_agreement
        rows.append([t.suite, f"{t.small} -> {t.large}", len(t.candidates),
                     ", ".join(t.candidates) or "none", num(a["tau_b"], 3),
                     interval(a.get("tau_b_ci") or (float("nan"),) * 2, 3),
                     num(a["p_value"], 3), num(min_exact_kendall_p(len(t.candidates)), 3),
                     num(a["weighted_tau"], 3),
                     f"{num(t.agreement['tau_b'], 3)} ({len(t.encoders)})"])
    if not rows:
        return None
    return table(rows, ["suite", "small -> large", "n cand.", "candidates", "tau-b",
                        "tau-b 95% CI", "p (exact)", "min. attainable p", "weighted tau",
                        "tau-b over all (n)"])


def transfer_section(ctx: ReportContext) -> str:
    if not any(t.complete for t in ctx.transfers):
        ran = sorted({r.backbone for r in ctx.rankings}) or ["none"]
        return (f"_No transfer to measure: it needs both backbones of a suite with grafts of "
                f"the same encoders; backbones with grafts here: {', '.join(ran)}._")
    sizes = sorted({len(t.encoders) for t in ctx.transfers if t.complete} | {4})
    min_ps = ", ".join(f"n = {n}: p >= {num(min_exact_kendall_p(n), 3)}" for n in sizes)
    parts = [
        "Kendall tau-b (scipy.stats.kendalltau, variant b; exact p where there are no ties) and "
        "top-weighted tau (scipy.stats.weightedtau on -MSE, so agreement among the best encoders "
        "counts most) between the two backbones' mean rankings, over encoders run on both. "
        "Its interval: both backbones' means drawn by the rankings' hierarchical bootstrap "
        "(releases, seeds, held-out episodes, windows; one draw of the shared suite's episodes "
        "for both), percentile.",
        f"**With so few encoders tau cannot reach significance**: the smallest two-sided p "
        f"scipy's exact method can give (perfect agreement) is {min_ps}. Read tau as a "
        f"description, not a test.",
    ]
    rows, notes = [], []
    for t in ctx.transfers:
        if not t.complete:
            notes.append(f"{t.suite} ({t.small} -> {t.large}): {t.missing}")
            continue
        a = t.agreement
        rows.append([t.suite, f"{t.small} -> {t.large}", len(t.encoders), num(a["tau_b"], 3),
                     interval(a.get("tau_b_ci") or (float("nan"),) * 2, 3),
                     num(a["p_value"], 3), num(t.min_p, 3), num(a["weighted_tau"], 3),
                     t.small_winner, yes_no(t.small_winner_in_large_tier), t.large_winner,
                     yes_no(t.large_winner_in_small_tier),
                     ctx.wrapper_text(t.small, t.suite), ctx.wrapper_text(t.large, t.suite)])
        if "note" in a:
            notes.append(f"{t.suite}: {a['note']}")
    if rows:
        parts.append(table(rows, ["suite", "small -> large", "n enc.", "tau-b", "tau-b 95% CI",
                                  "p (exact)",
                                  "min. attainable p", "weighted tau", "small winner",
                                  "in large top tier", "large winner", "in small top tier",
                                  "wrapper Δ small", "wrapper Δ large"]))
    candidates = candidate_transfer_table(ctx)
    if candidates:
        parts += [CANDIDATES_TEXT, candidates]
    if notes:
        parts.append(bullets(notes))
    s = ctx.support
    parts.append(SUPPORT_RULES)
    parts.append(f"**{s['comparisons_supporting']} of {s['comparisons_total']} backbone-suite "
                 f"comparisons and {s['seed_cells_supporting']} of {s['seed_cells_total']} "
                 f"seed-level cells support backbone-dependent rankings.**")
    if s["comparisons"]:
        parts.append(table([[c['suite'], f"{c['source']} -> {c['target']}",
                             yes_no(c["supports"])] for c in s["comparisons"]],
                           ["suite", "source winner -> target tier", "supports"]))
    return "\n\n".join(parts)


def tie_section(ctx: ReportContext) -> str:
    if not any(r.encoders for r in ctx.rankings):
        return "_No ranking: no tie band._"
    rows = [[r.backbone, r.suite, r.leader, ", ".join(r.top_tier), len(r.top_tier),
             yes_no(len(r.top_tier) > 1),
             ", ".join(f"{cell_label(s)}: {w}" for s, w in r.seed_winners.items()),
             yes_no(r.seed_sensitive)] for r in ctx.rankings if r.encoders]
    return "\n\n".join([TIER_RULE, table(rows, ["backbone", "suite", "leader", "top tier",
                                                "tier size", "near-tie", "per-seed winners",
                                                "seed-sensitive"])])


def seed_section(ctx: ReportContext) -> str:
    if not any(r.seed_winners for r in ctx.rankings):
        return "_No ranking: no per-seed winners._"
    parts = ["Per-seed winners (lowest normalised MSE within one seed):"]
    rows = []
    for r in ctx.rankings:
        for seed, winner in r.seed_winners.items():
            value = next(e.per_seed[PRIMARY][seed] for e in r.encoders if e.encoder == winner)
            rows.append([r.backbone, r.suite, seed, winner, num(value)])
    parts.append(table(rows, ["backbone", "suite", "seed", "winner", "winner norm. MSE"]))
    cells = [c for t in ctx.transfers if t.complete for c in t.seed_cells]
    parts.append("Seed-level cells (one seed of each backbone; supports = winners differ):")
    if cells:
        parts.append(table(
            [[c.suite, f"{c.small} -> {c.large}", c.small_seed, c.large_seed, len(c.encoders),
              c.small_winner, c.large_winner, num(c.agreement["tau_b"], 3),
              num(c.agreement["weighted_tau"], 3), yes_no(c.supports)] for c in cells],
            ["suite", "small -> large", "small seed", "large seed", "n enc.", "small winner",
             "large winner", "tau-b", "weighted tau", "supports"]))
    else:
        parts[-1] = "Seed-level cells: none (they need grafts on both backbones of a suite)."
    return "\n\n".join(parts)


def wrapper_section(ctx: ReportContext) -> str:
    rows = []
    for cd in ctx.controls:
        if not get_kind(cd.kind).tower:
            continue
        rows.append([cd.backbone, cd.suite, cell_label(cd.cell), num(cd.reference_mse.get(PRIMARY)),
                     num(cd.mse[PRIMARY]), pct(cd.delta.get(PRIMARY)), pct(cd.delta.get(RAW)),
                     "" if cd.reference_found else f"reference {cd.reference_id} missing"])
    for (b, s), wn in sorted(ctx.wrapper.items()):
        if wn.mean:
            rows.append([b, s, "mean", "", "", pct(wn.mean[PRIMARY]), pct(wn.mean[RAW]), ""])
    intro = ("Wrapper neutrality delta = (native_wrapped - native) / native on mean MSE, per "
             "seed and averaged over seeds. 0 would mean the wrapper alone costs nothing; the "
             "published study found +45..56% on SmolVLA and -50..52% on pi0.5.")
    if not rows:
        return "_No native_wrapped cells: the wrapper's neutrality is not measured here._"
    return intro + "\n\n" + table(rows, ["backbone", "suite", "seed", "native norm. MSE",
                                         "wrapped norm. MSE", "Δ norm.", "Δ raw", "note"])


def vision_section(ctx: ReportContext) -> str:
    """Best graft vs blind / zero-image controls, per backbone x suite (VISION_RULE)."""
    rows = []
    for v in ctx.vision:
        if not v.checked:
            rows.append([v.backbone, v.suite, v.best_encoder or "n/a", num(v.best_mse), "none",
                         "", "", "", "", UNCHECKED_HINT])
        for c in v.comparisons:
            rows.append([v.backbone, v.suite, v.best_encoder, num(v.best_mse), c.control,
                         ", ".join(map(str, c.seeds)), num(c.control_mse), num(c.diff, 3),
                         interval(c.diff_ci, 3),
                         "graft better" if c.better else "**FLAGGED: not better**"])
    notes = [f"{v.backbone} x {v.suite}: {n}" for v in ctx.vision for n in v.notes]
    if not rows:
        return "_No graft cells: no vision check._"
    parts = [VISION_RULE + f" {ctx.n_resamples} replicates.",
             table(rows, ["backbone", "suite", "best graft", "graft norm. MSE", "control",
                          "seeds", "control norm. MSE", "control - graft",
                          f"{CONFIDENCE:.0%} CI", "verdict"])]
    if notes:
        parts.append(bullets(notes))
    return "\n\n".join(parts)


def controls_section(ctx: ReportContext) -> str:
    rows = [[cd.backbone, cd.suite, cd.label, cd.seed, num(cd.mse[PRIMARY]), cd.reference_id,
             num(cd.reference_mse.get(PRIMARY)) if cd.reference_found else "missing",
             pct(cd.delta.get(PRIMARY)), pct(cd.delta.get(RAW))] for cd in ctx.controls]
    intro = ("Every control cell against its reference record: delta = (control - reference) / "
             "reference. zero_image / shuffled_image near 0 means the policy barely uses vision; "
             "lora and pooling show whether a little backbone capacity or another token grid "
             "moves the score.")
    if not rows:
        return "_No control cells in the results._"
    return intro + "\n\n" + table(rows, ["backbone", "suite", "control", "seed", "norm. MSE",
                                         "reference", "reference norm. MSE", "Δ norm.",
                                         "Δ raw"])


def plots_section(ctx: ReportContext) -> str:
    # The screen's scatter is drawn in its own section, once (it was printed twice).
    figures = [(title, path) for title, path in ctx.plots if title != SCATTER_TITLE]
    if not figures:
        return "_No figures (plots turned off, or no cells with data to draw)._"
    base = ctx.out_path.parent
    return "\n\n".join(f"![{title}]({path.relative_to(base).as_posix()})"
                       for title, path in figures)
