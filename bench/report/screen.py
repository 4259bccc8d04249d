"""REPORT.md's screen section (`pytest bench --screen`): the screen table, each tier's agreement
with the graft with intervals, each tier's measured cost, what the screen dropped and why, and a
scatter of each proxy against the graft's MSE per backbone x suite.

Pure apart from `screen_agreements`' bootstrap: stored screens, selections and graft records in,
markdown out; an undefined value prints as "undefined: <reason>", never as a number."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

from bench.analysis.agreement import STATISTICS, TIE_RULE, Interval, Undefined
from bench.analysis.candidates import candidate_items
from bench.analysis.family_scale import screening_rungs
from bench.analysis.tiers import (ALL, CANDIDATES, MIN_CANDIDATES, MIN_ENCODERS,
                                  graft_per_window, short_graft_agreement, short_tier,
                                  small_model_agreement, tier_agreement)
from bench.grid.kinds import SHORT_GRAFT, get_kind
from bench.report.format import num, table
from bench.report.naive import AT_REPORT_TIME, with_naive_baselines
from bench.report.screen_cost import (SMALL_MODEL_COST_HEADERS, SMALL_MODEL_COST_TEXT, cost_table,
                                      small_model_cost_rows)
from bench.screen.proxies import (INPUT_SETS, PROXIES, label_free_proxies, naive_proxies,
                                  proxy_names, supervised_proxies)
from bench.screen.records import GAIN, HELDOUT, VALUE

SECTION_TITLE = "Screening many encoders"
AGREEMENT_INTRO = (
    "**Agreement with the graft**, on two item sets: **all** the encoders with both a score and "
    "a graft (needs {all}), and the **candidates** a team would choose between (needs "
    "{candidates}): encoders whose registry entry runs trained weights in this world "
    "(bench.analysis.candidates), never random twins, known-answer encoders (pixels, blind, the "
    "ladder) or the tiny world's random-init stand-ins. The graft is the normalised held-out "
    "MSE, mean over releases and seeds; intervals: the paired hierarchical bootstrap "
    "(releases, seeds within a release, held-out episodes, windows within an episode; both "
    "tiers and the graft on one draw, docs/INTERVALS.md), {n} resamples. Naive "
    "baselines, scored exactly as a proxy: parameter count, FLOPs at the input size (torch's "
    "FLOP counter, the encoder as built) and input resolution, bigger ranked better; ImageNet "
    "top-1 is none of them, as no real encoder's own package card states one. Each tier's "
    "tau-b minus the best naive baseline's (the best re-chosen in every replicate) has its "
    "interval on the same draws as the tier's own statistics.")  # a report has it when its store holds screens
SCATTER_TITLE = "Screen proxies against the graft's MSE"


def measure(value, digits: int = 4) -> str:
    """A number, or 'undefined: reason'."""
    return f"undefined: {value.reason}" if isinstance(value, Undefined) else num(value, digits)


def screen_table(screens: Sequence) -> str:
    """One row per screened (backbone, suite, encoder), columns from the proxy table: each
    supervised proxy's gain of the features over the state, then the [state, features] value of
    those that show it (ridge and k-NN MSE), each label-free proxy's value, each naive
    baseline's value, the seconds."""
    gains, label_free, naive = supervised_proxies(), label_free_proxies(), naive_proxies()
    valued = [p for p in gains if p.value_column]
    with_features = INPUT_SETS[-1]
    # Entropy lies in [0, 1] and is not a difference: 3 digits tell encoders apart there.
    rows = [[s.backbone, s.suite, s.encoder]
            + [measure(s.value(p.name, GAIN)) for p in gains]
            + [measure(s.value(p.name, with_features)) for p in valued]
            + [measure(s.value(p.name, HELDOUT), 3) for p in label_free]
            + [measure(s.value(p.name, VALUE), 3) for p in naive] + [num(s.seconds, 2)]
            for s in sorted(screens, key=lambda s: (s.backbone, s.suite, s.encoder))]
    return table(rows, ["backbone", "suite", "encoder"] + [f"{p.label} gain" for p in gains]
                 + [p.value_column for p in valued] + [p.label for p in label_free]
                 + [p.label for p in naive] + ["s"])


def _with_interval(point, interval) -> str:
    text = measure(point, 3)
    if isinstance(interval, Interval):
        text += f" [{num(interval.low, 3)}, {num(interval.high, 3)}]"
    return text


def naive_text(a) -> str:
    """A tier's tau-b minus the best naive baseline's, its paired interval and which baseline."""
    if a.tier in {p.name for p in naive_proxies()}:
        return "(a naive baseline)"
    if a.naive_gap is None:
        return "n/a"
    best = f" vs {PROXIES[a.best_naive].label}" if a.best_naive else ""
    return _with_interval(a.naive_gap, a.naive_gap_interval) + best


def agreement_table(agreements: Sequence, with_naive: bool = True) -> str:
    """One row per (backbone, suite, item set, cheaper tier) with the point statistic and its
    paired hierarchical bootstrap interval, or why it was not measured; the tier's tau-b minus the
    best naive baseline's (paired) and whether the screen recommends it (`with_naive`: tiers
    measured beside the screens' naive baselines); then the tie rule."""
    naive = 2 if with_naive else 0
    rows = []
    for a in agreements:
        head = [a.backbone, a.suite, a.item_set, a.tier, len(a.encoders)]
        if a.missing or a.point is None:
            rows.append(head + [a.missing or "not measured"] + [""] * (len(STATISTICS) - 1 + naive))
            continue
        rows.append(head + [_with_interval(getattr(a.point, k), a.intervals.get(k))
                            for k in STATISTICS]
                    + [naive_text(a), "yes" if a.recommended else "no"][:naive])
    headers = ["backbone", "suite", "items", "tier", "encoders", "Kendall tau-b", "weighted tau",
               "MMRV (MSE)", "top-1 regret (MSE)", "tau-b minus the best naive (paired)",
               "recommended"]
    return table(rows, headers[:len(headers) - 2 + naive]) + f"\n\nTies: {TIE_RULE}"


def recommendation_lines(agreements: Sequence) -> list[str]:
    """Per backbone x suite x item set: the tiers the screen recommends (tau-b above the best
    naive baseline's by a paired interval above 0), or that none is."""
    lines = []
    for key in sorted({(a.backbone, a.suite, a.item_set) for a in agreements},
                      key=lambda k: (k[0], k[1], k[2] != CANDIDATES)):
        rows = [a for a in agreements if (a.backbone, a.suite, a.item_set) == key]
        good = [f"{a.tier} ({naive_text(a)})" for a in rows if a.recommended]
        where = f"**{key[0]} x {key[1]}, {key[2]}**"
        if good:
            lines.append(f"- {where}: recommended: {'; '.join(good)}.")
        elif any(a.point is not None for a in rows):
            lines.append(f"- {where}: no proxy or short graft beats the best naive baseline "
                         "(its paired interval reaches 0 or below): rank by the graft.")
        else:
            lines.append(f"- {where}: not measured.")
    return lines


def _panels(screens: Sequence) -> list[tuple[str, str]]:
    return sorted({(s.backbone, s.suite) for s in screens})


def _panel_agreements(mine: Sequence, records: Sequence, backbone: str, suite: str,
                      n_resamples: int, seed: int, **kwargs) -> list:
    """Every proxy's, short graft's and smaller model's (a smaller size of the panel backbone's
    family, bench.analysis.family_scale) TierAgreement on one panel and item set; kwargs:
    tier_agreement's baselines, items and item_set (a naive baseline gets no baselines)."""
    out = []
    for proxy in PROXIES.values():
        scores = {s.encoder: s.score(proxy.name) for s in mine}
        own = {**kwargs, "baselines": None} if proxy.naive else kwargs
        out.append(tier_agreement(scores, records, backbone, suite, proxy.name, n_resamples,
                                  seed, **own))
    out += [short_graft_agreement(records, backbone, suite, v, n_resamples, seed, **kwargs)
            for v in get_kind(SHORT_GRAFT).variants]
    return out + [small_model_agreement(records, small, large, s, n_resamples, seed, **kwargs)
                  for small, large, s in screening_rungs(records)
                  if (large, s) == (backbone, suite)]


def screen_agreements(screens: Sequence, records: Sequence, n_resamples: int,
                      seed: int = 0, candidates: frozenset[str] | None = None) -> list:
    """TierAgreement per backbone x suite x item set (all, then the candidates: `candidates`,
    default bench.analysis.candidates' of `records`) x tier: each proxy's scores (`screens`:
    ScreenScores) and each short graft against the graft records, over the encoders with both,
    each beside the naive baselines (the screens' parameter count, FLOPs, resolution)."""
    candidates = candidate_items(records) if candidates is None else candidates
    out = []
    for backbone, suite in _panels(screens):
        mine = [s for s in screens if (s.backbone, s.suite) == (backbone, suite)]
        baselines = {p.name: {s.encoder: s.score(p.name) for s in mine} for p in naive_proxies()}
        for item_set, items in ((ALL, None), (CANDIDATES, candidates)):
            out += _panel_agreements(mine, records, backbone, suite, n_resamples, seed,
                                     baselines=baselines, items=items, item_set=item_set)
    return out


def scatter_points(screens: Sequence, records: Sequence) -> list[tuple[str, list, list, list]]:
    """[(panel title, proxy scores, graft MSE, encoder names)] per backbone x suite x proxy, over
    the encoders with a defined score and a graft (mean over seeds and windows); then each short
    graft tier with its -MSE as the score (higher is better, as a proxy's)."""
    panels = []
    for backbone, suite in _panels(screens):
        per_window, _ = graft_per_window(records, backbone, suite)
        mine = [s for s in screens if (s.backbone, s.suite) == (backbone, suite)
                and s.encoder in per_window]
        for proxy in proxy_names():
            both = [s for s in mine if not isinstance(s.score(proxy), Undefined)]
            if both:
                panels.append((f"{backbone} x {suite}: {proxy}",
                               [float(s.score(proxy)) for s in both],
                               [float(per_window[s.encoder].mean()) for s in both],
                               [s.encoder for s in both]))
        for variant in get_kind(SHORT_GRAFT).variants:
            short, _ = graft_per_window(records, backbone, suite, SHORT_GRAFT, variant)
            both = sorted(e for e in short if e in per_window)
            if both:
                panels.append((f"{backbone} x {suite}: {short_tier(variant)} (-MSE)",
                               [-float(short[e].mean()) for e in both],
                               [float(per_window[e].mean()) for e in both], both))
    return panels


def dropped_lines(selections: Sequence) -> list[str]:
    """What each --screen run grafted and dropped, with the score that decided it."""
    lines = []
    for sel in sorted(selections, key=lambda s: (s.backbone, s.suite)):
        keep = "all" if sel.keep is None else f"the best {sel.keep}"
        lines.append(f"- **{sel.backbone} x {sel.suite}**, {keep} by {sel.by}: grafted "
                     f"{', '.join(sel.kept) or 'none'}; references {', '.join(sel.references) or 'none'}"
                     + (f" ({sel.note})" if sel.note else ""))
        lines += [f"  - dropped `{e}`: {why}" for e, why in sorted(sel.dropped.items())]
    return lines


@dataclass
class Calibration:
    """A calibration study a selection named (--screen-calibration): its agreements per backbone
    x suite x tier, its own selections, or why it could not be read when the report was built."""

    path: str
    agreements: list = field(default_factory=list)  # TierAgreement
    selections: list = field(default_factory=list)  # ScreenSelection
    error: str | None = None


def calibrations(selections: Sequence, n_resamples: int, seed: int = 0) -> dict[str, Calibration]:
    """{results dir: Calibration} of every calibration study the selections name: the same
    agreement as the study's own report (screen_agreements over its screens and records)."""
    from bench.results.store import load_calibration

    out = {}
    for path in sorted({s.calibration for s in selections if s.calibration}):
        try:
            study = load_calibration(path)
        except (OSError, ValueError) as e:  # gone or emptied since the run: said, not raised
            out[path] = Calibration(path, error=str(e))
            continue
        screens, _ = with_naive_baselines([r.scores for r in study.screens], study.records)
        out[path] = Calibration(path, screen_agreements(screens, study.records, n_resamples,
                                                        seed), study.selections)
    return out


def calibration_parts(selections: Sequence, studies: dict[str, Calibration]) -> list[str]:
    """Per selection: the agreement of the calibration study it named, or, for a top-K run that
    named none, that it has none (a top-K run grafts what its screen liked, so it cannot
    measure the screen itself)."""
    parts = []
    for sel in sorted(selections, key=lambda s: (s.backbone, s.suite)):
        panel = f"**{sel.backbone} x {sel.suite}**"
        if sel.calibration is None:
            if sel.keep is not None:
                parts.append(f"{panel}: this top-K run names no calibration study, so how far "
                             "its screen can be trusted is not measured here (its grafts are "
                             "what the screen kept; the agreement above is over them, or not "
                             "measured). Fix: run `--screen --screen-keep all` into another "
                             "results dir and name it with `--screen-calibration RESULTS_DIR`.")
            continue
        study = studies.get(sel.calibration) or Calibration(sel.calibration, error="not read")
        where = f"the calibration study `{sel.calibration}`"
        rows = [a for a in study.agreements if (a.backbone, a.suite) == (sel.backbone, sel.suite)]
        if study.error is not None:
            parts.append(f"{panel}: {where} could not be read when this report was built "
                         f"({study.error}): no agreement quoted.")
        elif not rows:
            parts.append(f"{panel}: {where} has no screen on {sel.backbone} x {sel.suite}: it "
                         "has no agreement for this backbone x suite.")
        else:
            covered = {e for a in rows for e in a.encoders}
            mine = set(sel.kept) | set(sel.dropped) | set(sel.references)
            own = [s for s in study.selections if (s.backbone, s.suite) == (sel.backbone, sel.suite)
                   and s.keep is not None]
            parts.append(f"{panel}, as measured by {where} over its {len(covered)} encoder(s) "
                         f"with a graft ({', '.join(sorted(covered))}); {len(mine & covered)} of "
                         f"this run's {len(mine)} encoder(s) are among them"
                         + (f". That study itself grafted only its screen's best {own[0].keep}: "
                            "its agreement is over what its screen kept" if own else "")
                         + ".\n\n" + agreement_table(rows))
    return parts


def small_model_cost(records: Sequence) -> list[str]:
    """The small-model rung's cost table with its heading, or nothing without a rung."""
    rows = small_model_cost_rows(records)
    return [SMALL_MODEL_COST_TEXT, table(rows, SMALL_MODEL_COST_HEADERS)] if rows else []


def screen_section(ctx) -> str | None:
    """The section, or None when the store holds no screen (the report leaves it out)."""
    res = ctx.results
    if not res.screens and not res.screen_failures:
        return None
    screens = ctx.screens
    parts = ["Zero-training proxies per encoder from the stored features (`pytest bench "
             "--screen`): each supervised proxy's score is the gain of [state, features] over "
             "[state] alone on the grafts' held-out windows (higher is better); entropy is "
             "label-free. The short-graft tiers (short_1_8, short_1_4) are the graft trained "
             "for 1/8 and 1/4 of its steps (whole schedule, compressed), ranked by their own "
             "held-out MSE; `--screen-by short` ranks by short_1_4. Where the grid holds "
             "several sizes of a family (backbones/tiny_sizes.py), the family's smaller "
             "models' grafts are a rung too (`small model <name>`, against the largest). "
             "A screen averages each camera's token grid: what an encoder carries in "
             "where things are is lost here, not in the graft (docs/SCREENING.md).", screen_table(screens) if screens else "_No finished screen._"]
    if res.screen_failures:
        parts.append("Screens that failed (their grafts are dropped): " + "; ".join(
            f"`{f.screen_id}`: {f.error}" for f in res.screen_failures))
    if ctx.naive_filled:
        parts.append(f"Naive baselines of {len(ctx.naive_filled)} screen(s) {AT_REPORT_TIME}: "
                     + ", ".join(f"`{s}`" for s in ctx.naive_filled) + ".")
    parts += [AGREEMENT_INTRO.format(all=MIN_ENCODERS, candidates=MIN_CANDIDATES,
                                     n=ctx.n_resamples),
              agreement_table(ctx.screen_agreements),
              "**What the screen recommends** (a tier whose tau-b beats the best naive "
              "baseline's by a paired interval above 0; the candidates first)",
              "\n".join(recommendation_lines(ctx.screen_agreements)) or "_Nothing measured._",
              "**Cost per encoder** (seconds: the screen's own solve, extraction not counted; "
              "each graft tier's wall time per cell, mean over seeds; screen / graft per encoder, "
              "then the mean and the worst: the ladder's goal is at most 5% for every encoder)",
              cost_table(res.screens, ctx.records),
              *small_model_cost(ctx.records),
              "**What the screen dropped**",
              "\n".join(dropped_lines(res.selections)) or "_No --screen selection stored._"]
    calibration = calibration_parts(res.selections, ctx.screen_calibrations)
    if calibration:
        parts += ["**The agreement of the calibration study this run names** "
                  "(`--screen-calibration`; its own records, recomputed here)", *calibration]
    scatter = [p for t, p in ctx.plots if t == SCATTER_TITLE]
    if scatter:
        parts.append(f"![{SCATTER_TITLE}]({scatter[0].relative_to(ctx.out_path.parent).as_posix()})")
    return "\n\n".join(parts)
