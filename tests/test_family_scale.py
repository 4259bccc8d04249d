"""Family or scale (bench.analysis.family_scale): known answers on fabricated ladder grids. A
ranking planted to flip with family but not size is called "family", one that flips with size
"size", equal rankings "neither"; the verdict is read on the candidates, with intervals."""

from __future__ import annotations

import json

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


# -- the small model as a rung of the screen, and the report's section ------------------------

SIX = {"a": 0.10, "b": 0.12, "c": 0.14, "d": 0.16, "e": 0.18, "f": 0.20}  # MIN_ENCODERS items
SIX_DOWN = {e: SIX[k] for e, k in zip(SIX, reversed(list(SIX)))}


def test_the_small_model_rung_agrees_with_the_large_as_planted():
    from bench.analysis.tiers import small_model_agreement

    same = ladder_records({"smolvla": SIX, "smolvla_l": SIX})
    rung = small_model_agreement(same, "smolvla", "smolvla_l", "spatial", RESAMPLES)
    assert rung.tier == "small model smolvla" and rung.backbone == "smolvla_l"
    assert rung.point.tau_b == pytest.approx(1.0) and rung.point.top1_regret == 0.0
    assert rung.intervals["tau_b"].low == pytest.approx(1.0)
    flipped = ladder_records({"smolvla": SIX, "smolvla_l": SIX_DOWN})
    rung = small_model_agreement(flipped, "smolvla", "smolvla_l", "spatial", RESAMPLES)
    assert rung.point.tau_b == pytest.approx(-1.0)
    assert rung.point.top1_regret == pytest.approx(0.10, rel=0.05)  # a's 0.20 vs d's 0.10
    assert rung.intervals["tau_b"].high == pytest.approx(-1.0)


def test_a_small_model_with_other_cells_is_drawn_per_window_and_says_so():
    from bench.analysis.tiers import small_model_agreement

    records = (ladder_records({"smolvla": SIX}, releases=2, seeds=2)
               + ladder_records({"smolvla_l": SIX}, releases=1, seeds=1))
    rung = small_model_agreement(records, "smolvla", "smolvla_l", "spatial", RESAMPLES)
    assert rung.tier == "small model smolvla (its cells not drawn)"
    assert rung.missing is None and rung.intervals["tau_b"].replicates == RESAMPLES


def test_the_report_says_family_or_scale_with_the_small_model_rung_and_its_cost(tmp_path):
    from bench.report.build import build_report
    from tests.factories import save_record

    levels = {**{b: SIX for b in ("smolvla", "smolvla_l")},
              **{b: SIX_DOWN for b in ("pi05_s", "pi05_l")}}
    for record in ladder_records(levels):
        save_record(tmp_path / "res", record)
    text = build_report(tmp_path / "res", tmp_path / "REPORT.md", n_resamples=RESAMPLES,
                        plots=False).read_text()
    section = text.split("## Family or scale")[1].split("\n## ")[0]
    assert ("**spatial** (on all encoders): the ranking changes with family, not with size "
            "(size: 0 of 2 comparisons change the choice; family: 2 of 2") in section
    assert "smolvla (0.41M) -> smolvla_l (13.91M)" in section
    assert section.count("| small model smolvla ") == 2  # all items; the candidates: not measured
    assert "| spatial | pi05_s        | pi05_l        | 4" in section  # its cost: 4 s a cell each
    assert "100.0%" in section
    summary = json.loads((tmp_path / "REPORT_summary.json").read_text())
    assert summary["family_scale"][0]["verdict"] == FAMILY


def test_the_small_model_cost_is_the_median_cell_not_the_one_that_trained_a_release():
    """A cell that first loads an untrained release holds its native training in its seconds
    (studies/family_scale: one pi05_l cell 2,063 s, the others ~440): the rung's cost is the
    median cell, so that one does not move it (the mean would read 28.8 s here, not 4)."""
    from bench.report.screen_cost import small_model_cost_rows

    records = ladder_records({"pi05_s": UP, "pi05_l": UP})
    first = next(i for i, r in enumerate(records) if r.backbone == "pi05_l")
    records[first] = records[first].replace(
        timings_s={**records[first].run.timings_s, "total": 400.0})
    assert records[first].run.total_s == 400.0
    assert small_model_cost_rows(records) == [["spatial", "pi05_s", "pi05_l", "4", "4", "100.0%"]]


def test_a_report_without_two_sizes_to_compare_has_no_section(tmp_path):
    from bench.report.build import build_report
    from tests.factories import save_record

    for record in ladder_records({"smolvla": SIX, "pi05": SIX_DOWN}):
        save_record(tmp_path / "res", record)
    text = build_report(tmp_path / "res", tmp_path / "REPORT.md", n_resamples=RESAMPLES,
                        plots=False).read_text()
    assert "Family or scale" not in text and "small model" not in text


def test_the_screens_agreement_table_holds_the_small_model_rung(tmp_path):
    from bench.report.screen import agreement_table, screen_agreements
    from bench.results.store import load_results
    from tests.factories import make_calibration_study, save_record

    make_calibration_study(tmp_path / "res", SIX, backbone="smolvla_l")  # grafts and screens
    for record in ladder_records({"smolvla": SIX_DOWN}, releases=1):
        save_record(tmp_path / "res", record)
    results = load_results(tmp_path / "res")
    rows = screen_agreements([r.scores for r in results.screens], results.records, RESAMPLES)
    rung = [a for a in rows if a.tier.startswith("small model smolvla")]
    assert [(a.backbone, a.item_set) for a in rung] == [("smolvla_l", "all"),
                                                        ("smolvla_l", "candidates")]
    assert rung[0].point.tau_b == pytest.approx(-1.0)
    assert "| small model smolvla | 6          | -1 [-1, -1]" in agreement_table(rung)
