"""Family or scale: does the encoder ranking move with the backbone's size, its family, both, or
neither? Rank transfer taken apart over the tiny size ladder (backbones.tiny_sizes).

The study's two backbones differ in family and size at once. Over a grid of ladder sizes, per
suite, two kinds of comparison (each a bench.analysis.transfer.Transfer, source -> target):
- **size**: within a family, each smaller size -> the family's largest size present (the model a
  team deploys; the smaller one is what it could choose on);
- **family**: at each rung both families have (matched sizes), SmolVLA's size -> pi0.5's.
Each is measured on the candidates (bench.analysis.candidates; on all encoders when fewer than
two candidates were grafted, and the verdict says so): both backbones ranked by
bench.analysis.rankings (hierarchical intervals: releases, seeds, held-out episodes, windows, and
each ranking's top tier), tau-b, weighted tau and the relative top-1 regret both ways with
intervals from the same hierarchical draws (bench.analysis.transfer.transfer_intervals).

CHANGE_RULE decides whether a comparison changes the choice; a suite's verdict is which axes do.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Collection, Sequence

from backbones.tiny_sizes import RUNGS, TinySize, size_of
from bench.analysis.candidates import candidate_items
from bench.analysis.rankings import (DEFAULT_RESAMPLES, Ranking, WindowMismatchError,
                                     rank_encoders)
from bench.analysis.tiers import ALL, CANDIDATES, small_model_agreement
from bench.analysis.transfer import Transfer, transfer_intervals, transfer_pair
from bench.grid.kinds import GRAFT

SIZE, FAMILY = "size", "family"
BOTH, NEITHER = "both", "neither"
ALL_ITEMS, CANDIDATE_ITEMS = "all encoders", "the candidates"

CHANGE_RULE = (
    "A comparison **changes the choice** when the two backbones' top tiers share no encoder "
    "(a top tier: the leader, lowest mean normalised MSE over releases and seeds, and every "
    "encoder whose paired 95% difference interval to it contains 0; the hierarchical bootstrap "
    "over releases, seeds, held-out episodes and windows, docs/INTERVALS.md): no encoder is then "
    "among the best on both, whatever either backbone's near-ties hide. A suite's ranking "
    "**changes with size** when any within-family comparison (a smaller size against the "
    "family's largest) changes the choice, **with family** when any matched-size comparison "
    "across families does: both, one, or neither. How much: tau-b, the relative top-1 regret "
    "(the source's leader on the target, against the target's leader) and whether each top tier "
    "holds the other's leader, each with its interval."
)
# Why shared tier members and not "the source's leader is outside the target's tier": a leader
# inside a near-tie band is a coin flip of the noise, so that rule calls rankings that agree
# within their intervals changed about half the time (tests/test_family_scale.py plants one).


def _rung(size: TinySize) -> int:
    return RUNGS.index(size.rung)


@dataclass
class Comparison:
    """One comparison of a suite: `axis` SIZE or FAMILY, its Transfer (source = `small`)."""

    axis: str
    transfer: Transfer
    # Each ranking's top tier over the encoders both backbones ran (CHANGE_RULE).
    small_tier: list[str] = field(default_factory=list)
    large_tier: list[str] = field(default_factory=list)

    @property
    def changes(self) -> bool | None:
        """CHANGE_RULE; None when the transfer is incomplete (`transfer.missing` says why)."""
        if not self.transfer.complete or not (self.small_tier and self.large_tier):
            return None
        return not set(self.small_tier) & set(self.large_tier)

    def to_dict(self) -> dict:
        return {"axis": self.axis, "changes": self.changes, "small_tier": self.small_tier,
                "large_tier": self.large_tier, **self.transfer.to_dict()}


@dataclass
class SuiteVerdict:
    """Both axes of one suite, over `items` (CANDIDATE_ITEMS or ALL_ITEMS); `outside`: the
    suite's backbones that are not ladder sizes (not compared here)."""

    suite: str
    items: str
    comparisons: list[Comparison] = field(default_factory=list)
    outside: list[str] = field(default_factory=list)

    def on(self, axis: str) -> list[Comparison]:
        return [c for c in self.comparisons if c.axis == axis]

    def changes(self, axis: str) -> bool | None:
        """Does the ranking change along `axis`: True when any comparison changes the choice,
        False when every one was measured and none does, None when none was measured."""
        known = [c.changes for c in self.on(axis) if c.changes is not None]
        if any(known):
            return True
        return False if known and len(known) == len(self.on(axis)) else None

    @property
    def verdict(self) -> str:
        """SIZE, FAMILY, BOTH or NEITHER when both axes were measured; else what one axis says
        and that the other was not measured, or 'not measured'."""
        says = {SIZE: self.changes(SIZE), FAMILY: self.changes(FAMILY)}
        unknown = [axis for axis, v in says.items() if v is None]
        if len(unknown) == 2:
            return "not measured: no complete comparison along size or family"
        if unknown:
            (axis,) = [a for a in says if a not in unknown]
            return (f"{axis if says[axis] else 'not ' + axis} (the {unknown[0]} axis not "
                    "measured)")
        if says[SIZE] and says[FAMILY]:
            return BOTH
        return SIZE if says[SIZE] else FAMILY if says[FAMILY] else NEITHER

    def to_dict(self) -> dict:
        return {"suite": self.suite, "items": self.items, "verdict": self.verdict,
                "changes_with_size": self.changes(SIZE),
                "changes_with_family": self.changes(FAMILY), "outside": self.outside,
                "comparisons": [c.to_dict() for c in self.comparisons]}


def ladder_pairs(backbones: Collection[str]) -> list[tuple[str, str, str]]:
    """(axis, source, target) of every comparison among `backbones` (names): each smaller size
    of a family -> its largest present (SIZE), then each rung both families hold (FAMILY,
    SmolVLA's size first). Backbones outside the ladder take no part."""
    sizes = sorted((size_of(b) for b in backbones if size_of(b) is not None), key=_rung)
    families = sorted({s.family for s in sizes}, key=lambda f: f != "smolvla")
    pairs = []
    for family in families:
        mine = [s for s in sizes if s.family == family]
        pairs += [(SIZE, s.name, mine[-1].name) for s in mine[:-1]]
    for rung in RUNGS:
        at = [s for f in families for s in sizes if s.family == f and s.rung == rung]
        pairs += [(FAMILY, at[0].name, other.name) for other in at[1:]]
    return pairs


def _ranking(records: Sequence, backbone: str, suite: str, n_resamples: int,
             seed: int) -> Ranking:
    try:
        return rank_encoders(records, backbone, suite, n_resamples=n_resamples,
                             random_seed=seed)
    except WindowMismatchError as err:
        return Ranking(backbone=backbone, suite=suite, error=str(err))


def suite_verdict(records: Sequence, suite: str, candidates: Collection[str] | None = None, *,
                  n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> SuiteVerdict:
    """Both axes of `suite` over its graft records: on the candidate encoders when at least two
    of them were grafted there (`candidates`: labels; None: every encoder)."""
    grafts = [r for r in records if r.kind == GRAFT and r.suite == suite]
    picked = [r for r in grafts if candidates is not None and r.encoder in candidates]
    items = CANDIDATE_ITEMS if len({r.encoder for r in picked}) >= 2 else ALL_ITEMS
    grafts = picked if items == CANDIDATE_ITEMS else grafts
    backbones = sorted({r.backbone for r in grafts})
    out = SuiteVerdict(suite, items, outside=[b for b in backbones if size_of(b) is None])
    pairs = ladder_pairs(backbones)
    rankings = {b: _ranking(grafts, b, suite, n_resamples, seed)
                for b in {name for _, *names in pairs for name in names}}
    for axis, a, b in pairs:
        t = transfer_pair(suite, rankings[a], rankings[b], a, b)
        out.comparisons.append(Comparison(
            axis, t, [e for e in rankings[a].top_tier if e in t.encoders],
            [e for e in rankings[b].top_tier if e in t.encoders]))
    transfer_intervals([c.transfer for c in out.comparisons], grafts,
                       n_resamples=n_resamples, seed=seed)
    return out


def family_scale(records: Sequence, candidates: Collection[str] | None = None, *,
                 n_resamples: int = DEFAULT_RESAMPLES, seed: int = 0) -> list[SuiteVerdict]:
    """One SuiteVerdict per suite whose graft records hold a comparison (two sizes of a family,
    or a matched pair across families); [] when none does (the report leaves its section out)."""
    out = []
    for suite in sorted({r.suite for r in records if r.kind == GRAFT}):
        backbones = {r.backbone for r in records if r.kind == GRAFT and r.suite == suite}
        if ladder_pairs(backbones):
            out.append(suite_verdict(records, suite, candidates, n_resamples=n_resamples,
                                     seed=seed))
    return out


def screening_rungs(records: Sequence) -> list[tuple[str, str, str]]:
    """(small, large, suite) of every smaller ladder size with grafts on a suite where its
    family's largest size present has grafts too: "screen on the small model of the family",
    a rung of the screen's ladder for that large model (bench.analysis.tiers
    small_model_agreement)."""
    out = []
    for suite in sorted({r.suite for r in records if r.kind == GRAFT}):
        backbones = {r.backbone for r in records if r.kind == GRAFT and r.suite == suite}
        out += [(small, large, suite) for axis, small, large in ladder_pairs(backbones)
                if axis == SIZE]
    return out


def small_model_agreements(records: Sequence, candidates: Collection[str] | None = None, *,
                           n_resamples: int = 1000, seed: int = 0) -> list:
    """TierAgreement of every screening rung, over all encoders and over the candidates (the
    screen's two item sets; `candidates` default: bench.analysis.candidates' of `records`;
    bench.analysis.tiers.small_model_agreement)."""
    candidates = candidate_items(records) if candidates is None else candidates
    return [small_model_agreement(records, small, large, suite, n_resamples, seed,
                                  items=items, item_set=item_set)
            for small, large, suite in screening_rungs(records)
            for item_set, items in ((ALL, None), (CANDIDATES, candidates))]
