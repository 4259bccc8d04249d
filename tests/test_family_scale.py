"""Family or scale (bench.analysis.family_scale): known answers on fabricated ladder grids. A
ranking planted to flip with family but not size is called "family", one that flips with size
"size", equal rankings "neither"; the verdict is read on the candidates, with intervals."""

from __future__ import annotations

import pytest

from bench.analysis.family_scale import (ALL_ITEMS, BOTH, CANDIDATE_ITEMS, FAMILY, NEITHER, SIZE,
                                         family_scale, ladder_pairs, suite_verdict)
from bench.grid.kinds import GRAFT
from bench.results.record import cell_id
from tests.factories import make_record

SMOLVLA = ("smolvla", "smolvla_m", "smolvla_l")
PI05 = ("pi05_s", "pi05_m", "pi05_l")
UP = {"a": 0.10, "b": 0.12, "c": 0.14, "d": 0.16}  # a leads by 20%: far outside the noise
DOWN = {e: UP[k] for e, k in zip(UP, reversed(list(UP)))}  # the same levels, d leads
RESAMPLES = 200


def ladder_records(levels: dict[str, dict[str, float]], releases: int = 2, seeds: int = 2,
                   suite: str = "spatial") -> list:
    """Graft records {backbone: {encoder: level}} over releases x seeds, with window noise and a
    small release effect (so every level of the intervals has something to draw)."""
    out = []
    for backbone, by_encoder in levels.items():
        for encoder, level in by_encoder.items():
            for release in range(releases):
                for seed in range(seeds):
                    record = make_record(backbone=backbone, suite=suite, encoder=encoder,
                                         seed=seed, level=level * (1 + 0.01 * release),
                                         noise=0.003)
                    out.append(record.replace(release=release, cell_id=cell_id(
                        GRAFT, backbone, suite, encoder, seed, None, release)))
    return out


def verdict(levels, candidates=None):
    return suite_verdict(ladder_records(levels), "spatial", candidates, n_resamples=RESAMPLES)


def test_the_pairs_are_each_smaller_size_to_the_largest_and_each_matched_rung():
    assert ladder_pairs(SMOLVLA + PI05 + ("pi05", "pi0")) == [
        (SIZE, "smolvla", "smolvla_l"), (SIZE, "smolvla_m", "smolvla_l"),
        (SIZE, "pi05", "pi05_l"), (SIZE, "pi05_s", "pi05_l"), (SIZE, "pi05_m", "pi05_l"),
        (FAMILY, "smolvla", "pi05_s"), (FAMILY, "smolvla_m", "pi05_m"),
        (FAMILY, "smolvla_l", "pi05_l")]
    # today's two base builds are different rungs of different families: nothing to compare
    assert ladder_pairs(["smolvla", "pi05"]) == []


def test_a_ranking_that_flips_with_family_but_not_size_is_called_family():
    found = verdict({**{b: UP for b in SMOLVLA}, **{b: DOWN for b in PI05}})
    assert found.verdict == FAMILY
    assert found.changes(SIZE) is False and found.changes(FAMILY) is True
    for c in found.on(FAMILY):
        t = c.transfer
        assert (t.small_winner, t.large_winner) == ("a", "d")
        assert t.agreement["tau_b"] == pytest.approx(-1.0)
        assert t.agreement["top1_regret"] == pytest.approx(0.6, rel=0.05)  # a on pi0.5: +60%
        lo, hi = t.agreement["top1_regret_ci"]
        assert 0.4 < lo <= t.agreement["top1_regret"] <= hi < 0.8
        assert t.agreement["tau_b_ci"] == [-1.0, -1.0]
    for c in found.on(SIZE):
        assert c.transfer.large_winner_in_small_tier is True
        assert c.transfer.agreement["tau_b"] == pytest.approx(1.0)
        assert c.transfer.agreement["top1_regret"] == 0.0


def test_equal_rankings_are_neither():
    found = verdict({b: UP for b in SMOLVLA + PI05})
    assert found.verdict == NEITHER
    assert len(found.on(SIZE)) == 4 and len(found.on(FAMILY)) == 3
    assert all(c.changes is False for c in found.comparisons)


def test_a_near_tie_whose_nominal_leader_differs_is_no_change():
    """On smolvla_l, b leads a by 0.1% (inside the noise: both in its top tier); on smolvla, a
    leads clearly. The tiers share a: no change, though the leaders differ and b lies outside
    smolvla's tier (the rule a leader-based verdict would break on)."""
    tied = {**UP, "a": 0.1001, "b": 0.1000}
    found = verdict({"smolvla": UP, "smolvla_l": tied, "pi05_s": UP, "pi05_l": tied})
    size = found.on(SIZE)[0]
    assert (size.transfer.small_winner, size.transfer.large_winner) == ("a", "b")
    assert size.small_tier == ["a"] and sorted(size.large_tier) == ["a", "b"]
    assert size.transfer.large_winner_in_small_tier is False
    assert size.changes is False and found.verdict == NEITHER


def test_a_ranking_that_flips_at_the_largest_size_in_both_families_is_called_size():
    levels = {"smolvla": UP, "smolvla_m": UP, "smolvla_l": DOWN,
              "pi05_s": UP, "pi05_m": UP, "pi05_l": DOWN}
    found = verdict(levels)
    assert found.verdict == SIZE
    assert [c.changes for c in found.on(SIZE)] == [True] * 4
    assert [c.changes for c in found.on(FAMILY)] == [False] * 3


def test_both_axes_and_a_missing_axis_are_said():
    both = verdict({"smolvla": UP, "smolvla_l": DOWN, "pi05_s": DOWN, "pi05_l": DOWN})
    assert both.verdict == BOTH
    one_family = verdict({"smolvla": UP, "smolvla_l": UP})
    assert one_family.verdict == "not size (the family axis not measured)"


def test_the_verdict_is_read_on_the_candidates():
    """`blind`, no candidate, leads everywhere by far: over all encoders nothing changes; over
    the candidates the planted family flip is found."""
    levels = {**{b: {**UP, "blind": 0.05} for b in SMOLVLA},
              **{b: {**DOWN, "blind": 0.05} for b in PI05}}
    assert verdict(levels).verdict == NEITHER
    on_candidates = verdict(levels, candidates=frozenset("abcd") | {"native"})
    assert on_candidates.items == CANDIDATE_ITEMS and on_candidates.verdict == FAMILY
    assert verdict(levels, candidates=frozenset({"a"})).items == ALL_ITEMS  # one: too few


def test_only_suites_with_a_comparison_get_a_verdict_and_other_backbones_stay_outside():
    records = (ladder_records({"smolvla": UP, "smolvla_l": UP, "pi0": DOWN})
               + ladder_records({"smolvla": UP, "pi05": DOWN}, suite="object"))
    found = family_scale(records, n_resamples=RESAMPLES)
    assert [v.suite for v in found] == ["spatial"]
    assert found[0].outside == ["pi0"] and found[0].verdict.startswith("not size")
