"""bench.analysis.tiers: a cheaper tier against graft records, by hand, with what is left out."""

from __future__ import annotations

import pytest

from bench.analysis.agreement import Undefined
from bench.analysis.tiers import MIN_ENCODERS, tier_agreement
from tests.factories import make_record

ENCODERS = [f"timm:model_{i}" for i in range(7)]
LEVELS = {e: 0.05 + 0.01 * i for i, e in enumerate(ENCODERS)}  # model_0 best


def grafts(seeds=(0, 1)):
    return [make_record(encoder=e, level=level, seed=s, noise=0.001)
            for e, level in LEVELS.items() for s in seeds]


def test_a_perfect_proxy_agrees_with_intervals():
    out = tier_agreement({e: -level for e, level in LEVELS.items()}, grafts(), "smolvla",
                         "spatial", "ridge", n_resamples=200)
    assert out.missing is None and out.encoders == sorted(ENCODERS)
    assert out.point.tau_b == pytest.approx(1.0) and out.point.mmrv == 0.0
    assert out.point.top1_regret == 0.0
    assert out.intervals["tau_b"].low == pytest.approx(1.0)
    assert out.graft_mse[0] == pytest.approx(0.05)


def test_a_wrong_pick_costs_its_regret_in_mse():
    scores = {e: -level for e, level in LEVELS.items()}
    scores["timm:model_3"] = 1.0  # the proxy's pick; its graft MSE is 0.08, the best 0.05
    out = tier_agreement(scores, grafts(), "smolvla", "spatial", "logme", n_resamples=50)
    assert out.point.top1_regret == pytest.approx(0.03)
    assert out.point.tau_b < 1.0


def test_too_few_encoders_is_not_measured_and_undefined_scores_are_left_out():
    scores = {e: -level for e, level in LEVELS.items()}
    scores["timm:model_0"] = Undefined("all 4 feature columns constant")
    scores["timm:model_1"] = Undefined("too few windows")
    scores["timm:extra"] = 1.0  # screened, never grafted
    out = tier_agreement(scores, grafts(), "smolvla", "spatial", "knn")
    assert out.missing.startswith("not measured: 5 encoder(s)") and str(MIN_ENCODERS) in out.missing
    assert "constant" in out.left_out["timm:model_0"]
    assert out.left_out["timm:extra"] == "no graft record"
    assert out.point is None


def test_unpaired_windows_are_refused():
    records = grafts(seeds=(0,))
    records[0] = make_record(encoder=ENCODERS[0], level=0.05, window_ids=list(range(24)))
    out = tier_agreement({e: 0.0 for e in ENCODERS}, records, "smolvla", "spatial", "ridge")
    assert "not paired" in out.missing


def test_report_tables_print_numbers_intervals_and_reasons():
    from bench.report.screen import agreement_table, screen_table
    from bench.screen.records import ScreenScores

    ok = tier_agreement({e: -level for e, level in LEVELS.items()}, grafts(), "smolvla",
                        "spatial", "ridge", n_resamples=50)
    short = tier_agreement({ENCODERS[0]: 1.0}, grafts(), "pi05", "spatial", "knn")
    text = agreement_table([ok, short])
    row = next(line for line in text.splitlines() if "smolvla" in line)
    assert [c.strip() for c in row.strip("|").split("|")][:6] == [
        "smolvla", "spatial", "all", "ridge", "7", "1 [1, 1]"]
    assert "not measured: 0 encoder(s)" in text and "Ties: Scores tie when exactly equal" in text
    screen = ScreenScores("blind", "smolvla", "spatial", seconds=0.4,
                          entropy=Undefined("every token norm is 0"))
    screen.proxies = {p: {"gain": 0.0, "state+features": 0.3} for p in ("logme", "ridge", "knn")}
    assert "undefined: every token norm is 0" in screen_table([screen])


def test_the_report_section_from_a_store_of_screens(tmp_path):
    """Seven stored screens whose ridge gain orders them as their grafts do, a selection: the
    report's screen section measures the agreement with intervals, and lists what was dropped."""
    from bench.report.build import build_report
    from bench.screen.records import ScreenFailure, ScreenSelection
    from tests.factories import make_calibration_study

    store = make_calibration_study(tmp_path / "results", LEVELS)
    store.write_screen(ScreenFailure("smolvla", "spatial", "timm:broken", "OSError: no file"))
    store.write_selection(ScreenSelection("smolvla", "spatial", "ridge", 2, tuple(ENCODERS[:2]),
                                          ("pixels",), {ENCODERS[6]: "ridge rank 7 of 7 (-0.11)"}))
    text = build_report(store.root, tmp_path / "REPORT.md", n_resamples=50).read_text()
    section = text[text.index("## Screening many encoders"):text.index("## Plots")]
    row = next(line for line in section.splitlines() if "| ridge " in line and "| 7 " in line)
    assert "1 [1, 1]" in row  # tau-b 1 with its interval
    assert "| entropy " in section and "undefined" in section  # entropy ties: no order
    assert "`smolvla-spatial-timm_broken`: OSError: no file" in section
    assert f"dropped `{ENCODERS[6]}`: ridge rank 7 of 7" in section
    assert "screen_scatter.png" in section and (tmp_path / "REPORT_plots" / "screen_scatter.png").is_file()
    # A top-K selection naming no calibration study says it has none.
    assert "this top-K run names no calibration study" in section


def test_a_top_k_run_quotes_the_calibration_study_it_names_or_why_not(tmp_path):
    """The report's calibration part (bench.report.screen.calibration_parts): the named study's
    agreement per backbone x suite with its path; a study without that backbone x suite, or gone
    since the run, is said in words, never as numbers."""
    from bench.report.screen import calibration_parts, calibrations
    from bench.screen.records import ScreenSelection
    from tests.factories import make_calibration_study

    study = str(make_calibration_study(tmp_path / "calib", LEVELS).root)
    named = [ScreenSelection("smolvla", "spatial", "logme", 2, ("timm:model_0", "mine"),
                             ("pixels",), {"other": "logme rank 3 of 3"}, calibration=study),
             ScreenSelection("pi05", "spatial", "logme", 2, ("a",), (), calibration=study)]
    [pi05, smolvla] = calibration_parts(named, calibrations(named, n_resamples=50))  # sorted
    assert f"the calibration study `{study}` over its 7 encoder(s)" in smolvla
    assert "1 of this run's 4 encoder(s) are among them" in smolvla
    logme = next(line for line in smolvla.splitlines() if "| logme " in line)
    assert [c.strip() for c in logme.strip("|").split("|")][2:6] == ["all", "logme", "7",
                                                                      "1 [1, 1]"]  # tau-b
    assert "has no screen on pi05 x spatial" in pi05 and "[" not in pi05
    moved = [ScreenSelection("smolvla", "spatial", "logme", 2, (), (),
                             calibration=str(tmp_path / "gone"))]
    [gone] = calibration_parts(moved, calibrations(moved, 50))
    assert "could not be read when this report was built (no such results dir)" in gone


def test_the_short_graft_tier_against_the_graft_by_hand():
    """Short grafts (kind short_graft) whose MSE keeps the graft's order, but for one swap at
    1/8: tau-b 1 at 1/4; at 1/8 one discordant pair of 21 and the regret of its wrong pick."""
    from bench.analysis.tiers import short_graft_agreement
    from bench.grid.kinds import SHORT_GRAFT

    swapped = {**LEVELS, "timm:model_0": 0.061, "timm:model_1": 0.06}  # 1/8 picks model_1
    shorts = [make_record(kind=SHORT_GRAFT, encoder=e, variant=v, level=2 * levels[e],
                          noise=0.001)
              for v, levels in (("1_4", LEVELS), ("1_8", swapped)) for e in ENCODERS]
    records = grafts(seeds=(0,)) + shorts
    quarter = short_graft_agreement(records, "smolvla", "spatial", "1_4", n_resamples=100)
    assert quarter.tier == "short_1_4" and quarter.missing is None
    assert quarter.point.tau_b == pytest.approx(1.0) and quarter.point.top1_regret == 0.0
    assert quarter.predicted[0] == pytest.approx(-0.10)  # -(its MSE): higher is better
    assert "tau_b" in quarter.intervals
    eighth = short_graft_agreement(records, "smolvla", "spatial", "1_8", n_resamples=100)
    assert eighth.point.tau_b == pytest.approx(1 - 2 / 21)  # (20 - 1) / 21
    assert eighth.point.top1_regret == pytest.approx(0.01)  # model_1's graft 0.06 - 0.05
    assert short_graft_agreement(grafts(), "smolvla", "spatial", "1_4").missing.startswith(
        "not measured: 0 encoder(s)")
