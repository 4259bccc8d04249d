"""Rank transfer between backbones: Kendall tau-b, weighted tau, tier checks, support counts.

Rules (quoted verbatim in the report, see SUPPORT_RULES):
- A backbone-suite comparison is one suite and one DIRECTION source -> target between two
  backbones (small -> large and large -> small). It supports backbone-dependent rankings when
  the source backbone's winner (lowest mean normalised MSE over seeds) is NOT in the target
  backbone's top tier (leader plus encoders whose paired 95% difference interval contains 0).
  Two backbones x S suites give 2S comparisons.
- A seed-level cell is one suite and one pair (small-backbone seed, large-backbone seed). It
  supports backbone-dependent rankings when the two seeds' winners differ, winners taken over the
  encoders present in both seeds. Two backbones with s1 and s2 seeds give s1*s2 cells per suite.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from itertools import combinations
from typing import Sequence

import numpy as np
import scipy.stats

from bench.analysis.agreement import (Measure, Undefined, as_float, is_defined, kendall_p_value,
                                      kendall_tau_b, pairwise_tau_b, top1_regret, weighted_tau)
from bench.analysis.hierarchy import replicate_means
from bench.analysis.rankings import (PRIMARY, Ranking, WindowMismatchError, backbone_order,
                                     cell_arrays, graft_records)

SUPPORT_RULES = (
    "A **backbone-suite comparison** is one suite and one direction (source backbone -> target "
    "backbone, both directions counted). It *supports backbone-dependent rankings* when the "
    "source backbone's winner (lowest mean normalised MSE over seeds) is **not** in the target "
    "backbone's top tier. A **seed-level cell** is one suite and one pair (small-backbone seed, "
    "large-backbone seed); it supports backbone-dependent rankings when the two seeds' winners "
    "(over the encoders present in both) differ."
)


def relative_regret(mse_source: Sequence[float], mse_target: Sequence[float]) -> Measure:
    """Top-1 regret of choosing on the source backbone and deploying on the target, relative to
    the target's best: (target MSE of the source's leader - target's lowest MSE) / target's
    lowest MSE, >= 0 (bench.analysis.agreement.top1_regret's tie rule: the worst of tied picks).
    Relative, because MSE levels are not comparable across backbones."""
    target = np.asarray(mse_target, dtype=float)
    regret = top1_regret(-np.asarray(mse_source, dtype=float), -target)
    if not is_defined(regret):
        return regret
    if not target.min() > 0:
        return Undefined(f"the target's lowest MSE is {target.min()}: no relative regret")
    return float(regret / target.min())


def rank_agreement(mse_a: Sequence[float], mse_b: Sequence[float]) -> dict:
    """Kendall tau-b (scipy, exact p where no ties), top-weighted tau of two MSE vectors (n,),
    and the relative top-1 regret both ways (`top1_regret`: a's leader on b, `top1_regret_back`:
    b's leader on a; relative_regret).

    Lower MSE is better, so bench.analysis.agreement gets -MSE: weighted tau's hyperbolic
    weigher then weights agreement at the top of the ranking (best encoders) most. An undefined
    statistic is NaN here (the report prints n/a) and its reason is under "undefined"."""
    a, b = -np.asarray(mse_a, dtype=float), -np.asarray(mse_b, dtype=float)
    stats = {"tau_b": kendall_tau_b(a, b), "p_value": kendall_p_value(a, b),
             "weighted_tau": weighted_tau(a, b), "top1_regret": relative_regret(-a, -b),
             "top1_regret_back": relative_regret(-b, -a)}
    out: dict = {"n": len(a)} | {k: as_float(v) for k, v in stats.items()}
    undefined = {k: v.reason for k, v in stats.items() if not is_defined(v)}
    if undefined:
        out["undefined"] = undefined
    return out


def min_exact_kendall_p(n: int) -> float:
    """Smallest two-sided p that scipy's exact Kendall test can give for n items (NaN if n<2)."""
    if n < 2:
        return float("nan")
    return float(scipy.stats.kendalltau(np.arange(n), np.arange(n), method="exact").pvalue)


@dataclass
class SeedCell:
    suite: str
    small: str
    large: str
    small_seed: int | str  # a seed, or 'rel<r>-seed<s>' (bench.analysis.rankings.cell_key)
    large_seed: int | str
    encoders: list[str]
    small_winner: str | None
    large_winner: str | None
    agreement: dict
    supports: bool | None  # None when fewer than 2 common encoders


@dataclass
class Transfer:
    """Rank transfer small -> large backbone on one suite (`missing` says why it is partial)."""

    suite: str
    small: str
    large: str
    encoders: list[str] = field(default_factory=list)
    small_mse: list[float] = field(default_factory=list)
    large_mse: list[float] = field(default_factory=list)
    small_ranks: dict[str, int] = field(default_factory=dict)
    large_ranks: dict[str, int] = field(default_factory=dict)
    agreement: dict = field(default_factory=dict)
    min_p: float = float("nan")
    small_winner: str | None = None
    large_winner: str | None = None
    small_winner_in_large_tier: bool | None = None
    large_winner_in_small_tier: bool | None = None
    seed_cells: list[SeedCell] = field(default_factory=list)
    missing: str | None = None
    # The same agreement over the candidates among `encoders` (bench.analysis.candidates);
    # empty when no candidate set was given.
    candidates: list[str] = field(default_factory=list)
    candidate_agreement: dict = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return self.missing is None

    def to_dict(self) -> dict:
        return asdict(self)


def _cell_keys(ranking: Ranking) -> list:
    """The ranking's trained cells, as its per-cell tables key them (a seed, or
    'rel<r>-seed<s>' when several releases were measured)."""
    return list(dict.fromkeys(k for e in ranking.encoders for k in e.per_seed[PRIMARY]))


def _seed_cells(suite: str, small: Ranking, large: Ranking) -> list[SeedCell]:
    cells = []
    for s_small in _cell_keys(small):
        for s_large in _cell_keys(large):
            pairs = []
            for enc in small.encoders:
                other = next((e for e in large.encoders if e.encoder == enc.encoder), None)
                if other is None:
                    continue
                a = enc.per_seed[PRIMARY].get(s_small)
                b = other.per_seed[PRIMARY].get(s_large)
                if a is not None and b is not None:
                    pairs.append((enc.encoder, a, b))
            names = [p[0] for p in pairs]
            a = [p[1] for p in pairs]
            b = [p[2] for p in pairs]
            w_small = names[int(np.argmin(a))] if pairs else None
            w_large = names[int(np.argmin(b))] if pairs else None
            cells.append(SeedCell(
                suite=suite, small=small.backbone, large=large.backbone, small_seed=s_small, large_seed=s_large, encoders=names,
                small_winner=w_small, large_winner=w_large, agreement=rank_agreement(a, b),
                supports=(w_small != w_large) if len(pairs) >= 2 else None))
    return cells


def _on_candidates(t: Transfer, candidates: frozenset[str]) -> None:
    """t's agreement again over the candidates among its common encoders."""
    keep = [i for i, e in enumerate(t.encoders) if e in candidates]
    t.candidates = [t.encoders[i] for i in keep]
    t.candidate_agreement = rank_agreement([t.small_mse[i] for i in keep],
                                           [t.large_mse[i] for i in keep])


def transfer_pair(suite: str, small: Ranking | None, large: Ranking | None,
                  small_name: str, large_name: str,
                  candidates: frozenset[str] | None = None) -> Transfer:
    """Compare the rankings of two backbones on one suite, over every common encoder and, given
    `candidates` (labels), over the candidates among them; partial inputs set `missing`."""
    t = Transfer(suite=suite, small=small_name, large=large_name)
    problems = []
    for name, ranking in ((small_name, small), (large_name, large)):
        if ranking is None or not ranking.encoders:
            problems.append(f"{name} has no graft cells on {suite}")
        elif ranking.error:
            problems.append(f"{name} x {suite}: {ranking.error}")
    if problems:
        t.missing = "needs both backbones: " + "; ".join(problems)
        return t
    large_by_name = {e.encoder: e for e in large.encoders}
    common = [e for e in small.encoders if e.encoder in large_by_name]
    t.encoders = [e.encoder for e in common]
    t.small_mse = [e.mean[PRIMARY] for e in common]
    t.large_mse = [large_by_name[e.encoder].mean[PRIMARY] for e in common]
    t.small_ranks = {e.encoder: e.rank for e in small.encoders}
    t.large_ranks = {e.encoder: e.rank for e in large.encoders}
    t.agreement = rank_agreement(t.small_mse, t.large_mse)
    if candidates is not None:
        _on_candidates(t, candidates)
    t.min_p = min_exact_kendall_p(len(common))
    t.small_winner, t.large_winner = small.leader, large.leader
    if small.leader in large_by_name:
        t.small_winner_in_large_tier = small.leader in large.top_tier
    if large.leader in {e.encoder for e in small.encoders}:
        t.large_winner_in_small_tier = large.leader in small.top_tier
    t.seed_cells = _seed_cells(suite, small, large)
    only = sorted({e.encoder for e in small.encoders} ^ set(large_by_name))
    if len(common) < 2:
        t.missing = f"fewer than 2 encoders on both backbones (common: {t.encoders})"
    elif only:
        t.agreement["note"] = f"encoders on one backbone only, left out: {only}"
    return t


def transfer_all(rankings: Sequence[Ranking], backbones: Sequence[str] | None = None,
                 suites: Sequence[str] | None = None,
                 candidates: frozenset[str] | None = None) -> list[Transfer]:
    """One Transfer per suite and backbone pair (smaller backbone first).

    `backbones`/`suites` name what the grid should hold, so absent ones are reported as missing;
    `candidates`: the candidate labels, each transfer's agreement also given over them."""
    by_key = {(r.backbone, r.suite): r for r in rankings}
    backbones = backbone_order(list(backbones or []) + [r.backbone for r in rankings])
    suites = sorted(set(suites or []) | {r.suite for r in rankings})
    out = []
    for suite in suites:
        if len(backbones) < 2:
            out.append(Transfer(suite=suite, small=backbones[0] if backbones else "?",
                                large="?", missing=f"needs both backbones: only "
                                f"{backbones or 'none'} present in the results"))
            continue
        for small, large in combinations(backbones, 2):
            out.append(transfer_pair(suite, by_key.get((small, suite)),
                                     by_key.get((large, suite)), small, large, candidates))
    return out


def support_counts(transfers: Sequence[Transfer]) -> dict:
    """Counts of comparisons and seed-level cells supporting backbone-dependent rankings."""
    comparisons = []
    for t in transfers:
        if t.missing is not None:
            continue
        for source, target, inside in ((t.small, t.large, t.small_winner_in_large_tier),
                                       (t.large, t.small, t.large_winner_in_small_tier)):
            if inside is not None:
                comparisons.append({"suite": t.suite, "source": source, "target": target,
                                    "supports": not inside})
    seed_cells = [c for t in transfers if t.missing is None for c in t.seed_cells
                  if c.supports is not None]
    return {
        "comparisons_supporting": sum(c["supports"] for c in comparisons),
        "comparisons_total": len(comparisons),
        "comparisons": comparisons,
        "seed_cells_supporting": sum(c.supports for c in seed_cells),
        "seed_cells_total": len(seed_cells),
    }


def _draws(records: Sequence, backbone: str, suite: str, encoders: Sequence[str],
           n_resamples: int, seed: int) -> np.ndarray | None:
    """(n, B) hierarchical replicates of `encoders`' mean graft MSE on backbone x suite (the
    rankings' draw: releases, seeds, episodes, windows), None when they cannot be drawn."""
    cells = [r for r in graft_records(records, backbone, suite) if r.encoder in encoders]
    try:
        ca = cell_arrays(cells, lambda c: c.encoder, (PRIMARY,)) if cells else None
    except WindowMismatchError:
        return None
    if ca is None or sorted(ca.items) != sorted(encoders):
        return None
    reps = replicate_means(ca.values[PRIMARY], ca.units, n_resamples=n_resamples,
                           random_seed=seed)
    return reps.draws[[ca.items.index(e) for e in encoders]]


def _tau_interval(small: np.ndarray, large: np.ndarray, confidence: float = 0.95) -> list | None:
    """Percentile interval of tau-b over paired replicates (n, B) of two backbones' means."""
    taus = [pairwise_tau_b(-small[:, b], -large[:, b]) for b in range(small.shape[1])]
    kept = [t for t in taus if is_defined(t) and np.isfinite(t)]
    if not kept:
        return None
    alpha = (1 - confidence) / 2
    return [float(np.quantile(kept, alpha)), float(np.quantile(kept, 1 - alpha))]


def _regret_interval(source: np.ndarray, target: np.ndarray,
                     confidence: float = 0.95) -> list | None:
    """Percentile interval of relative_regret over paired replicates (n, B) of the source's and
    the target's means (the source's pick in each replicate, on the target's same replicate)."""
    values = [relative_regret(source[:, b], target[:, b]) for b in range(source.shape[1])]
    kept = [v for v in values if is_defined(v) and np.isfinite(v)]
    if not kept:
        return None
    alpha = (1 - confidence) / 2
    return [float(np.quantile(kept, alpha)), float(np.quantile(kept, 1 - alpha))]


def transfer_intervals(transfers: Sequence[Transfer], records: Sequence, *,
                       n_resamples: int = 1000, seed: int = 0) -> None:
    """Each complete transfer's tau-b interval (`agreement["tau_b_ci"]`, and the candidates'
    in `candidate_agreement`) and its relative top-1 regret's both ways (`top1_regret_ci`,
    `top1_regret_back_ci`): both backbones' encoder means drawn by the rankings' hierarchical
    bootstrap with one seed, so both draw the same held-out episodes of their shared suite."""
    for t in transfers:
        if not t.complete:
            continue
        sets = [(t.agreement, t.encoders)]
        if t.candidate_agreement:
            sets.append((t.candidate_agreement, t.candidates))
        for target, encoders in sets:
            if len(encoders) < 2:
                continue
            small = _draws(records, t.small, t.suite, encoders, n_resamples, seed)
            large = _draws(records, t.large, t.suite, encoders, n_resamples, seed)
            if small is not None and large is not None:
                target["tau_b_ci"] = _tau_interval(small, large)
                target["top1_regret_ci"] = _regret_interval(small, large)
                target["top1_regret_back_ci"] = _regret_interval(large, small)
