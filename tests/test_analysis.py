"""Known-answer tests of the statistics in bench.analysis.rankings*, on hand-made arrays and records."""

from __future__ import annotations

import numpy as np
import pytest

from bench.analysis.rankings import (
    WindowMismatchError, align_windows, encoder_means, paired_window_bootstrap, rank_all,
    rank_encoders, seed_winner_index, top_tier_mask,
)
from bench.analysis.controls import (
    UNCHECKED_HINT, control_deltas, relative_delta, vision_check, vision_checks,
    wrapper_neutrality,
)
from bench.analysis.transfer import (
    min_exact_kendall_p, rank_agreement, support_counts, transfer_all,
)
from tests.factories import make_grid, make_record

ENCODERS = ("siglip", "dinov2_s", "fastvit", "repvit")
RESAMPLES = 400  # enough for stable percentile intervals on these small, clean grids


def ranked(records):
    return rank_all(records, n_resamples=RESAMPLES)


# ---------------------------------------------------------------------------------------------
# pure functions over arrays


def test_encoder_means_by_hand():
    # 2 encoders x 2 seeds x 2 windows; encoder 1 lacks seed 1.
    per_window = np.array([[[1.0, 3.0], [2.0, 4.0]],
                           [[2.0, 2.0], [np.nan, np.nan]]])
    means, diffs = encoder_means(per_window, leader=1)
    np.testing.assert_allclose(means, [2.5, 2.0])
    # the difference uses only seed 0, the one both have: 2.0 - 2.0
    np.testing.assert_allclose(diffs, [0.0, 0.0])


def test_bootstrap_is_paired_on_windows():
    # Windows differ a lot in difficulty, encoders differ by a constant: a paired interval on
    # the difference is exactly that constant, while each mean's interval is wide.
    difficulty = np.linspace(0.0, 10.0, 30)
    per_window = np.stack([difficulty[None], difficulty[None] + 0.5])  # (2, 1, 30)
    result = paired_window_bootstrap(per_window, leader=0, n_resamples=RESAMPLES)
    assert result.diff[1] == pytest.approx(0.5)
    assert result.diff_lo[1] == pytest.approx(0.5) and result.diff_hi[1] == pytest.approx(0.5)
    assert result.mean_hi[0] - result.mean_lo[0] > 1.0
    assert result.diff_lo[0] == 0.0 and result.diff_hi[0] == 0.0


def test_bootstrap_is_reproducible_and_handles_one_window():
    x = np.random.default_rng(3).normal(1.0, 0.1, (3, 2, 12))
    a = paired_window_bootstrap(x, 0, n_resamples=200, random_seed=7)
    b = paired_window_bootstrap(x, 0, n_resamples=200, random_seed=7)
    np.testing.assert_array_equal(a.mean_lo, b.mean_lo)
    single = paired_window_bootstrap(x[..., :1], 0)
    assert np.isnan(single.mean_lo).all() and np.isfinite(single.mean).all()


def test_top_tier_mask_rule():
    lo = np.array([0.0, -0.1, 0.01, np.nan])
    hi = np.array([0.0, 0.2, 0.3, np.nan])
    assert top_tier_mask(lo, hi, leader=0).tolist() == [True, True, False, False]


def test_seed_winner_index():
    seed_means = np.array([[1.0, 3.0, np.nan], [2.0, 1.0, np.nan]])
    assert seed_winner_index(seed_means).tolist() == [0, 1, -1]


def test_min_exact_kendall_p_for_four_encoders():
    assert min_exact_kendall_p(4) == pytest.approx(1 / 12)  # 2/4! two-sided: never < 0.083
    assert min_exact_kendall_p(3) == pytest.approx(1 / 3)
    assert np.isnan(min_exact_kendall_p(1))


def test_rank_agreement_known_taus():
    same = rank_agreement([1, 2, 3, 4], [10, 20, 30, 40])
    assert same["tau_b"] == pytest.approx(1.0) and same["weighted_tau"] == pytest.approx(1.0)
    assert same["p_value"] == pytest.approx(1 / 12)
    swap_top = rank_agreement([1, 2, 3, 4], [2, 1, 3, 4])
    swap_bottom = rank_agreement([1, 2, 3, 4], [1, 2, 4, 3])
    assert swap_top["tau_b"] == pytest.approx(4 / 6) == swap_bottom["tau_b"]
    # the top-weighted tau punishes a swap at the top more than one at the bottom
    assert swap_top["weighted_tau"] < swap_bottom["weighted_tau"]


def test_relative_delta():
    assert relative_delta(0.15, 0.10) == pytest.approx(0.5)
    assert np.isnan(relative_delta(1.0, 0.0))


# ---------------------------------------------------------------------------------------------
# records -> rankings, transfer, controls


def levels(backbone, suite, values):
    return {(backbone, suite, e): v for e, v in zip(ENCODERS, values)}


def test_winner_flips_between_backbones():
    records = make_grid(levels("smolvla", "spatial", [0.070, 0.073, 0.076, 0.079])
                        | levels("pi05", "spatial", [0.0267, 0.0256, 0.0290, 0.0300]),
                        noise=0.001)
    rankings = ranked(records)
    smol, pi = (next(r for r in rankings if r.backbone == b) for b in ("smolvla", "pi05"))
    assert smol.leader == "siglip" and pi.leader == "dinov2_s"
    assert pi.top_tier == ["dinov2_s"]
    (t,) = transfer_all(rankings)
    assert (t.small, t.large) == ("smolvla", "pi05")
    assert t.agreement["tau_b"] == pytest.approx(4 / 6)  # one discordant pair of six
    assert t.small_winner_in_large_tier is False and t.large_winner_in_small_tier is False
    counts = support_counts([t])
    assert (counts["comparisons_supporting"], counts["comparisons_total"]) == (2, 2)
    assert (counts["seed_cells_supporting"], counts["seed_cells_total"]) == (4, 4)


def test_rankings_agree():
    records = make_grid(levels("smolvla", "object", [0.05, 0.06, 0.07, 0.08])
                        | levels("pi05", "object", [0.02, 0.025, 0.03, 0.035]))
    (t,) = transfer_all(ranked(records))
    assert t.agreement["tau_b"] == pytest.approx(1.0)
    assert t.agreement["weighted_tau"] == pytest.approx(1.0)
    assert t.small_winner_in_large_tier is True
    assert support_counts([t])["comparisons_supporting"] == 0


def test_near_tie_gives_a_top_tier_of_several():
    records = make_grid(levels("pi05", "object", [0.0200, 0.0201, 0.0200, 0.0300]),
                        seeds=(0, 1, 2), noise=0.004)
    (r,) = ranked(records)
    assert set(r.top_tier) == {"siglip", "dinov2_s", "fastvit"}
    assert r.encoders[-1].encoder == "repvit" and not r.encoders[-1].in_top_tier


def test_seed_sensitive_winner_is_visible():
    records = []
    for seed, (a, b) in enumerate([(0.020, 0.021), (0.022, 0.021)]):
        records += [make_record(backbone="pi05", suite="object", encoder="siglip", seed=seed,
                                level=a),
                    make_record(backbone="pi05", suite="object", encoder="fastvit", seed=seed,
                                level=b)]
    (r,) = ranked(records)
    assert r.seed_winners == {0: "siglip", 1: "fastvit"} and r.seed_sensitive


def paper_shaped_grid():
    """The published pattern: SigLIP wins SmolVLA; DINOv2 leads pi0.5 spatial; pi0.5 object is
    a seed-sensitive near-tie band. SmolVLA has 2 seeds, pi0.5 has 3 (12 seed-level cells)."""
    recs = make_grid(levels("smolvla", "spatial", [0.0706, 0.0734, 0.0760, 0.0790]), (0, 1))
    recs += make_grid(levels("pi05", "spatial", [0.0267, 0.0256, 0.0280, 0.0290]), (0, 1, 2))
    per_seed = {  # (backbone, encoder): levels per seed
        # fastvit far enough behind SmolVLA's leader that a seed draw cannot tie them (the
        # intervals draw seeds: siglip's two seeds straddle dinov2_s's, and those two tie)
        ("smolvla", "siglip"): [0.0490, 0.0506], ("smolvla", "dinov2_s"): [0.0505, 0.0505],
        ("smolvla", "fastvit"): [0.060, 0.060], ("smolvla", "repvit"): [0.062, 0.062],
        ("pi05", "siglip"): [0.0200, 0.0203, 0.0204], ("pi05", "dinov2_s"): [0.0203] * 3,
        ("pi05", "fastvit"): [0.0202, 0.0199, 0.0200], ("pi05", "repvit"): [0.025] * 3,
    }
    for (backbone, encoder), values in per_seed.items():
        for seed, level in enumerate(values):
            recs.append(make_record(backbone=backbone, suite="object", encoder=encoder,
                                    seed=seed, level=level, noise=0.004 if backbone == "pi05"
                                    else 0.0))
    return recs


def test_paper_shaped_grid_counts():
    rankings = ranked(paper_shaped_grid())
    by = {(r.backbone, r.suite): r for r in rankings}
    assert by["smolvla", "spatial"].leader == by["smolvla", "object"].leader == "siglip"
    assert by["pi05", "spatial"].leader == "dinov2_s"
    pi_object = by["pi05", "object"]
    assert len(pi_object.top_tier) >= 2 and "siglip" in pi_object.top_tier
    assert pi_object.seed_sensitive
    counts = support_counts(transfer_all(rankings))
    assert (counts["comparisons_supporting"], counts["comparisons_total"]) == (3, 4)
    assert (counts["seed_cells_supporting"], counts["seed_cells_total"]) == (11, 12)


def test_only_one_backbone_says_what_is_missing():
    records = make_grid(levels("smolvla", "spatial", [0.07, 0.08, 0.09, 0.10]))
    (t,) = transfer_all(ranked(records), backbones=["smolvla", "pi05"])
    assert not t.complete and "needs both backbones" in t.missing and "pi05" in t.missing
    assert support_counts([t])["comparisons_total"] == 0


def test_windows_aligned_by_id_and_mismatch_is_an_error():
    a = make_record(encoder="siglip", per_window=[1.0, 2.0, 3.0])
    b = make_record(encoder="dinov2_s", per_window=[3.5, 1.5, 2.5],
                    window_ids=[20, 0, 10])  # same windows, other order
    _, orders = align_windows([a, b])
    assert np.asarray(b.scores.per_window_in())[orders[1]].tolist() == [1.5, 2.5, 3.5]
    r = rank_encoders([a, b], "smolvla", "spatial", n_resamples=RESAMPLES)
    assert r.encoders[1].diff["normalized"] == pytest.approx(0.5)
    c = make_record(encoder="fastvit", per_window=[1.0, 2.0, 3.0], window_ids=[0, 10, 99])
    with pytest.raises(WindowMismatchError, match="99"):
        align_windows([a, c])
    (bad,) = rank_all([a, c], n_resamples=RESAMPLES)
    assert bad.error and not bad.encoders


def test_wrapper_neutrality_known_sign_and_size():
    records = make_grid({}, seeds=(0, 1), native={("smolvla", "spatial"): (0.10, 0.15),
                                                  ("pi05", "spatial"): (0.02, 0.01)})
    wn = wrapper_neutrality(records)
    assert wn["smolvla", "spatial"].mean["normalized"] == pytest.approx(0.5)
    assert wn["smolvla", "spatial"].per_seed[1]["raw"] == pytest.approx(0.5)
    assert wn["pi05", "spatial"].mean["normalized"] == pytest.approx(-0.5)


def test_control_deltas_against_reference_and_missing_reference():
    records = [make_record(encoder="pixels", level=0.2),
               make_record(kind="lora", encoder="pixels", level=0.1),
               make_record(kind="pooling", encoder="pixels", variant="global", level=0.3),
               make_record(kind="zero_image", encoder=None, variant="eval", level=0.4)]  # its native is absent
    deltas = {cd.cell_id: cd for cd in control_deltas(records)}
    assert deltas["smolvla-spatial-pixels-lora-seed0"].delta["normalized"] == pytest.approx(-0.5)
    assert deltas["smolvla-spatial-pixels-pool_global-seed0"].delta["raw"] == pytest.approx(0.5)
    zero = deltas["smolvla-spatial-native-zero_image_eval-seed0"]
    assert not zero.reference_found and zero.reference_id == "smolvla-spatial-native-seed0"


def test_native_reference_falls_back_to_any_seed_of_the_released_policy():
    records = [make_record(kind="native", seed=0, level=0.10),
               make_record(kind="native_wrapped", seed=1, level=0.05, reference=None)]
    (cd,) = control_deltas(records)
    assert cd.reference_id == "smolvla-spatial-native-seed0"
    assert cd.delta["normalized"] == pytest.approx(-0.5)


# ---------------------------------------------------------------------------------------------
# vision use: does the best graft beat its blind / zero-image control?

RAMP = [0.05 + 0.01 * i for i in range(12)]  # per-window graft MSE, 12 windows


def cells(encoder, values_per_seed, **kw):
    return [make_record(encoder=encoder, seed=seed, per_window=values, **kw)
            for seed, values in enumerate(values_per_seed)]


def check(records):
    return vision_check(records, "smolvla", "spatial", n_resamples=RESAMPLES)


def test_graft_that_clearly_beats_blind_is_not_flagged():
    # per-window difference blind - siglip is exactly +0.02 on every window and seed
    records = (cells("siglip", [RAMP, RAMP]) + cells("dinov2_s", [[v + 0.01 for v in RAMP]] * 2)
               + cells("blind", [[v + 0.02 for v in RAMP]] * 2))
    c = check(records)
    assert c.best_encoder == "siglip" and c.best_mse == pytest.approx(np.mean(RAMP))
    (cmp,) = c.comparisons
    assert cmp.control == "blind graft" and cmp.seeds == [0, 1]
    assert cmp.diff == pytest.approx(0.02)
    assert cmp.diff_ci == pytest.approx((0.02, 0.02)) and cmp.better
    assert c.status == "uses vision" and not c.flagged


def test_graft_no_better_than_blind_is_flagged():
    # blind = graft -/+ 0.01 on alternating windows: mean difference 0, interval straddles 0
    wobble = [v + (0.01 if i % 2 else -0.01) for i, v in enumerate(RAMP)]
    c = check(cells("siglip", [RAMP, RAMP]) + cells("blind", [wobble, wobble]))
    (cmp,) = c.comparisons
    assert cmp.diff == pytest.approx(0.0, abs=1e-12)
    assert cmp.diff_ci[0] < 0 < cmp.diff_ci[1] and not cmp.better
    assert c.flagged and c.status == "FLAGGED" and c.failed_controls == ["blind graft"]


def test_blind_leading_the_ranking_is_flagged_and_never_the_best_graft():
    c = check(cells("siglip", [RAMP]) + cells("blind", [[v - 0.01 for v in RAMP]]))
    assert c.best_encoder == "siglip"
    assert c.comparisons[0].diff == pytest.approx(-0.01) and c.flagged


def test_no_control_is_unchecked():
    records = cells("siglip", [RAMP]) + cells("dinov2_s", [[v + 0.01 for v in RAMP]])
    # a zero_image control of an encoder that is not the best one does not check the best
    records.append(make_record(kind="zero_image", encoder="dinov2_s", variant="train",
                               per_window=RAMP))
    records.append(make_record(kind="shuffled_image", encoder="siglip", per_window=RAMP))
    c = check(records)
    assert c.best_encoder == "siglip"
    assert c.comparisons == [] and not c.checked and not c.flagged
    assert c.status == "unchecked" and "blind or zero_image" in UNCHECKED_HINT


def test_pooled_over_seeds_is_the_mean_of_per_seed_paired_differences():
    # seed 0: blind worse by 0.04 on every window; seed 1: identical. Pooled: +0.02.
    records = cells("siglip", [RAMP, RAMP]) + cells("blind", [[v + 0.04 for v in RAMP], RAMP])
    (cmp,) = check(records).comparisons
    # the seeds are drawn: the interval holds both seeds' differences (0.04 and 0), so it
    # cannot call the graft better on two seeds that disagree this much
    assert cmp.diff == pytest.approx(0.02)
    assert cmp.diff_ci[0] <= 0.0 and cmp.diff_ci[1] >= 0.04 and not cmp.better
    # a blind cell of a seed the graft lacks is not paired
    records.append(make_record(encoder="blind", seed=7, per_window=[9.0] * 12))
    assert check(records).comparisons[0].seeds == [0, 1]


def test_a_control_without_the_grafts_cells_is_named_not_compared():
    """A blind graft only on a seed the best graft lacks: a note naming its cells, no comparison."""
    records = cells("siglip", [RAMP]) + [make_record(encoder="blind", seed=3, per_window=RAMP)]
    c = check(records)
    assert not c.comparisons and c.status == "unchecked"
    assert c.notes == ["blind graft: no seed in common with the siglip graft (control (release, "
                       "seed) cells [(0, 3)])"]


def test_zero_image_controls_of_the_best_encoder_and_of_native():
    records = cells("siglip", [RAMP, RAMP, RAMP]) + [
        make_record(kind="zero_image", encoder="siglip", variant=variant, seed=seed,
                    per_window=[v + shift for v in RAMP],
                    cell_id=f"smolvla-spatial-siglip-zero_image_{variant}-seed{seed}")
        for variant, shift in (("train", 0.0), ("eval", 0.05)) for seed in (0, 1, 2)]
    # the released policy does not depend on the seed: its one cell pairs with every graft seed
    records.append(make_record(kind="zero_image", encoder=None, variant="eval", seed=0,
                               per_window=[v + 0.03 for v in RAMP]))
    c = check(records)
    by = {cmp.control: cmp for cmp in c.comparisons}
    assert set(by) == {"zero_image[eval] of siglip", "zero_image[train] of siglip",
                       "zero_image[eval] of native"}
    assert by["zero_image[eval] of native"].seeds == [0, 1, 2]
    assert by["zero_image[eval] of native"].diff == pytest.approx(0.03)
    assert by["zero_image[eval] of siglip"].better
    # the graft trained on zeroed images scores the same: vision adds nothing -> flagged
    assert not by["zero_image[train] of siglip"].better
    assert c.flagged and c.failed_controls == ["zero_image[train] of siglip"]


def test_vision_control_windows_are_paired_by_id():
    graft = make_record(encoder="siglip", per_window=RAMP)
    shuffled = list(range(12))[::-1]
    blind = make_record(encoder="blind", per_window=[RAMP[i] + 0.01 for i in shuffled],
                        window_ids=[10 * i for i in shuffled])
    (cmp,) = check([graft, blind]).comparisons
    assert cmp.diff_ci == pytest.approx((0.01, 0.01))
    other = make_record(encoder="blind", per_window=RAMP, window_ids=list(range(500, 512)))
    c = check([graft, other])
    assert not c.checked and "other held-out windows" in c.notes[0]


def test_vision_checks_cover_every_backbone_suite():
    records = (cells("siglip", [RAMP]) + cells("blind", [[v + 0.02 for v in RAMP]])
               + cells("siglip", [RAMP], backbone="pi05"))
    got = {(c.backbone, c.suite): c.status for c in vision_checks(records, n_resamples=100)}
    assert got == {("smolvla", "spatial"): "uses vision", ("pi05", "spatial"): "unchecked"}
