"""The tuned-encoder control (bench.grid.kinds tune_encoder): projector AND encoder train, nothing
else; the encoder runs in the loop from a private copy, at Protocol.encoder_lr; the cell is
deterministic; start-up refuses a selection it cannot run; the report's tuned-minus-frozen
analysis gives known answers."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import torch

from bench.analysis.tuning import (
    HELPS, HURTS, LIVE_HURTS, MOVED_HELPS, NOT_FLAT, ONE_SEED, UNCLEAR, last_quarter_change,
    tuned_vs_frozen,
)
from bench.grid.cells import CellSpec, control_cells, tunable_encoders
from bench.grid.kinds import CELL_KINDS, GRAFT, SAME, control_kinds
from bench.grid.protocol import PROFILES, TINY, with_overrides
from bench.results.store import ResultStore
from bench.loops.encode import encode_pooled
from bench.cell.plan import cell_context
from encoders import build_encoder
from tests.factories import make_record
from tests.worlds import lent_workspace

TUNED = next(k.name for k in CELL_KINDS.values() if k.tune_encoder)
PROFILE = with_overrides(TINY, steps=3)


def test_tuned_cells_read_as_the_cell_run_per_encoder_with_weights_and_in_the_loop():
    cell = CellSpec(TUNED, "pi05", "spatial", 0, "dinov2_s")
    assert f"test_control[{cell.id}]" == "test_control[pi05-spatial-dinov2_s-tuned_encoder-seed0]"
    assert cell.reference == CellSpec(GRAFT, "pi05", "spatial", 0, "dinov2_s")
    with pytest.raises(ValueError, match="needs an encoder"):
        CellSpec(TUNED, "pi05", "spatial", 0, None)
    # Every grid encoder with weights, not the control encoders; pixels/blind have none.
    profile = dataclasses.replace(TINY, controls=(TUNED,), control_encoders=("pixels",), seeds=(0, 1))
    assert tunable_encoders(("dinov2_s", "pixels", "blind", "nope")) == ("dinov2_s",)
    assert [c.id for c in control_cells(profile) if c.backbone == "smolvla"] == [
        "smolvla-spatial-dinov2_s-tuned_encoder-seed0",
        "smolvla-spatial-dinov2_s-tuned_encoder-seed1"]
    # Stored features are the frozen encoder's: its encoder runs in the loop, its projector is
    # its own (never the graft's), whatever the run's --features.
    context = cell_context(cell, "cache", projectors={})
    assert context.features_mode == "loop" and context.reuse is None and context.keep_as is None
    assert not cell.spec.shares_graft_training("dinov2_s", None)
    # Opt-in: no profile's default grid runs it (--controls or a grid file names it).
    assert all(TUNED not in p.controls for p in PROFILES.values()) and TUNED in control_kinds()


def test_start_up_refuses_a_misspelt_kind_and_a_tuned_control_without_encoder_weights():
    from bench.options import build_profile
    from bench.startup import check_tuned_encoders

    class Config:  # what build_profile reads of pytest's config
        def __init__(self, **given):
            self.given = given

        def getoption(self, name):
            return self.given.get(name)

    with pytest.raises(pytest.UsageError, match=r"--controls tuned_encodr: unknown control kind"):
        build_profile(Config(**{"--controls": "tuned_encodr"}))
    blind = build_profile(Config(**{"--controls": TUNED, "--encoders": "pixels,blind"}))
    labels = {"controls": f"--controls {TUNED}", "encoders": "--encoders pixels,blind"}
    with pytest.raises(pytest.UsageError, match=r"^--controls tuned_encoder: tuned_encoder needs "
                       r"an encoder's weights in the loop, and no encoder of --encoders pixels,blind"):
        check_tuned_encoders(blind, labels)
    check_tuned_encoders(dataclasses.replace(blind, encoders=("pixels", "dinov2_s")), labels)


def _trained(tmp_path, backbone: str):
    """A tuned cell built and trained by the runner's own steps; (cell, ws, graft)."""
    from bench.cell.runner import build_graft, cell_inputs, train_graft

    ws = lent_workspace(PROFILE, ResultStore(tmp_path / "results"))
    cell = CellSpec(TUNED, backbone, "spatial", 0, "dinov2_s")
    context = cell_context(cell, "cache")
    bb = ws.backbone(backbone, "spatial")
    inputs = cell_inputs(cell, PROFILE.protocol, ws.suite("spatial"), ws.split("spatial"), bb,
                         torch.device("cpu"))
    graft = build_graft(cell, ws, bb, inputs, context)
    return cell, ws, bb, graft, lambda: train_graft(cell, ws, bb, graft, context)


def test_tuned_cell_trains_exactly_projector_and_encoder(tmp_path, monkeypatch):
    """By count (requires_grad over policy, projector, encoder), by the optimiser's groups (the
    encoder at encoder_lr), and by bits: the backbone and the session's encoder are unchanged
    after training, the cell's encoder copy changed, and evaluation reads the tuned copy."""
    cell, ws, bb, graft, train = _trained(tmp_path, "smolvla")
    shared = ws.encoder("dinov2_s")
    encoder = graft.inputs.encoder
    assert encoder is not shared and graft.inputs.features is None  # private, in the loop
    n_encoder = sum(p.numel() for p in shared.parameters())
    n_projector = sum(p.numel() for p in graft.projector.parameters())
    trainable = {id(p) for m in (bb.policy, graft.projector, encoder)
                 for p in m.parameters() if p.requires_grad}
    assert trainable == {id(p) for m in (graft.projector, encoder) for p in m.parameters()}
    assert graft.encoder_params == n_encoder > 0

    groups = []
    adamw = torch.optim.AdamW

    class Spy(adamw):
        def __init__(self, params, **kwargs):
            super().__init__(params, **kwargs)
            groups.extend((g["lr"], {id(p) for p in g["params"]}) for g in self.param_groups)

    monkeypatch.setattr(torch.optim, "AdamW", Spy)
    policy_before = {k: v.clone() for k, v in bb.policy.state_dict().items()}
    shared_before = {k: v.clone() for k, v in shared.state_dict().items()}
    copy_before = {k: v.clone() for k, v in encoder.state_dict().items()}
    train()
    p = PROFILE.protocol
    assert groups == [(p.lr, {id(q) for q in graft.projector.parameters()}),
                      (p.encoder_lr, {id(q) for q in encoder.parameters()})]
    assert all(torch.equal(v, bb.policy.state_dict()[k]) for k, v in policy_before.items())
    assert all(torch.equal(v, shared.state_dict()[k]) for k, v in shared_before.items())
    moved = [k for k, v in copy_before.items() if not torch.equal(v, encoder.state_dict()[k])]
    assert len(moved) == len([q for q in encoder.parameters()])  # every weight, no buffer
    frames = ws.split("spatial").windows[:4]
    scored = graft.inputs.eval_features(SAME)(torch.arange(4), frames)
    images = ws.suite("spatial").images(frames)
    for k, v in encode_pooled(encoder, images, graft.inputs.grid).items():
        assert torch.equal(scored[k], v)
        assert not torch.equal(v, encode_pooled(shared, images, graft.inputs.grid)[k])


def test_tuned_cell_twice_gives_the_same_bits_and_records_its_parameters(tmp_path):
    from bench.cell.service import run_cell

    cell = CellSpec(TUNED, "smolvla", "spatial", 0, "dinov2_s")
    runs = [run_cell(cell, lent_workspace(PROFILE, ResultStore(tmp_path / f"r{i}")))
            for i in range(2)]
    a, b = runs
    assert a.scores.per_window == b.scores.per_window
    assert a.training.loss_curve == b.training.loss_curve
    assert a.measured.features_mode == "loop" and a.measured.feature_dtype is None
    n_encoder = sum(p.numel() for p in build_encoder("dinov2_s", "tiny").parameters())
    assert a.training.trainable_params == a.training.projector_params + n_encoder
    assert a.measured.protocol["encoder_lr"] == PROFILE.protocol.encoder_lr


# --- the report's analysis: known answers ----------------------------------------------------
# A frozen twin whose loss has flattened (its last quarter no lower than the quarter before).
FLAT = [[0, 1.0], [25, 0.5], [50, 0.3], [60, 0.31], [75, 0.3], [90, 0.3], [99, 0.31]]


def _pair(encoder: str, frozen: list[float], tuned: list[float], seed: int = 0, **kw):
    return [make_record(encoder=encoder, seed=seed, per_window=frozen, loss_curve=FLAT, **kw),
            make_record(kind=TUNED, encoder=encoder, seed=seed, per_window=tuned, **kw)]


def _seeds(encoder: str, frozen: list[float], tuned: list[float], **kw):
    """The same pair on seeds 0 and 1: a verdict needs two seeds."""
    return [r for seed in (0, 1) for r in _pair(encoder, frozen, tuned, seed=seed, **kw)]


def test_tuned_minus_frozen_known_answers_and_the_ranking_change():
    """A constant per-window gap is the difference and its whole interval; a gap that flips
    sign across windows is unclear; tuning reverses A and B: the ranking (and leader) change."""
    base = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    records = (_seeds("dinov2_s", base, [v - 0.5 for v in base])  # helps: -0.5 everywhere
               + _seeds("siglip", [v - 0.2 for v in base], [v + 0.3 for v in base])  # hurts
               + _seeds("fastvit", base, [v + (0.4 if i % 2 else -0.4)
                                          for i, v in enumerate(base)]))  # unclear
    study = tuned_vs_frozen(records, n_resamples=200)
    got = {c.encoder: c for c in study.comparisons}
    assert got["dinov2_s"].diff == pytest.approx(-0.5)
    assert got["dinov2_s"].diff_ci == pytest.approx((-0.5, -0.5))
    assert got["dinov2_s"].relative == pytest.approx(-0.5 / 3.5)
    assert got["siglip"].diff == pytest.approx(0.5) and got["siglip"].verdict == HURTS
    assert got["dinov2_s"].verdict == HELPS and got["fastvit"].verdict == UNCLEAR
    (ranking,) = study.rankings
    assert ranking.frozen_order == ["siglip", "dinov2_s", "fastvit"]  # 3.3 < 3.5 = 3.5 (names)
    assert ranking.tuned_order == ["dinov2_s", "fastvit", "siglip"]  # 3.0 < 3.5 < 3.8
    assert ranking.changed and ranking.leader_changed


def test_one_seed_gives_no_verdict():
    """The same -0.5 everywhere on one seed: the difference is reported, the verdict is not."""
    base = [1.0, 2.0, 3.0, 4.0]
    (only,) = tuned_vs_frozen(_pair("dinov2_s", base, [v - 0.5 for v in base]),
                              n_resamples=50).comparisons
    assert only.diff == pytest.approx(-0.5) and only.verdict == ONE_SEED


def test_pairs_only_common_seeds_and_says_what_it_cannot_pair():
    base = np.linspace(1, 2, 6).tolist()
    records = (_pair("dinov2_s", base, [v - 0.1 for v in base], seed=0)
               + [make_record(encoder="dinov2_s", seed=1, per_window=base),
                  make_record(kind=TUNED, encoder="siglip", seed=0, per_window=base)])
    study = tuned_vs_frozen(records, n_resamples=50)
    (c,) = study.comparisons
    assert c.seeds == [0] and c.diff == pytest.approx(-0.1)
    assert study.notes == ["smolvla x spatial: siglip: no seed with both a tuned cell and a "
                           "frozen graft of as many steps (tuned seeds [0], frozen seeds [])"]
    assert tuned_vs_frozen(records[:1]).comparisons == []  # no tuned cell: nothing to say


def test_a_tuned_cell_is_paired_with_the_frozen_graft_of_as_many_steps():
    """tuned_encoder_1_8 (75 steps) against the short_1_8 graft, the full tuned cell (600)
    against the graft: two questions, two rankings; never a 75-step cell against a 600-step one."""
    short_kind = next(k for k in CELL_KINDS.values() if k.tier)
    tuned_short = next(k.name for k in CELL_KINDS.values()
                       if k.tune_encoder and k.scaled_steps(600, None) == 75)
    short_variant = next(v for v in short_kind.variants if short_kind.scaled_steps(600, v) == 75)
    base = [1.0, 2.0, 3.0, 4.0]
    records = [make_record(encoder="dinov2_s", per_window=base, train_steps=600),
               make_record(kind=TUNED, encoder="dinov2_s", per_window=[v - 0.5 for v in base],
                           train_steps=600),
               make_record(kind=short_kind.name, variant=short_variant, encoder="dinov2_s",
                           per_window=[v + 1.0 for v in base], train_steps=75),
               make_record(kind=tuned_short, encoder="dinov2_s", per_window=[v + 1.2 for v in base],
                           train_steps=75)]
    study = tuned_vs_frozen(records, n_resamples=50)
    got = {c.steps: c for c in study.comparisons}
    assert sorted(got) == [75, 600] and not study.notes
    assert got[600].frozen_mse == pytest.approx(2.5) and got[600].diff == pytest.approx(-0.5)
    assert got[75].frozen_mse == pytest.approx(3.5) and got[75].diff == pytest.approx(0.2)
    assert [r.steps for r in study.rankings] == [600, 75]
    # The controls section's reference is the same step-matched twin.
    assert CellSpec(tuned_short, "smolvla", "spatial", 0, "dinov2_s").reference.id == \
        records[2].cell_id
    assert CellSpec(TUNED, "smolvla", "spatial", 0, "dinov2_s").reference.id == records[0].cell_id
    assert records[3].reference == records[2].cell_id
    # Without its short twin, the 1/8 cell is named as unpaired, not compared with the graft.
    alone = tuned_vs_frozen([r for r in records if r.kind != short_kind.name], n_resamples=50)
    assert [c.steps for c in alone.comparisons] == [600]
    assert alone.notes == ["smolvla x spatial: dinov2_s at 75 steps: no seed with both a tuned "
                           "cell and a frozen graft of as many steps (tuned seeds [0], frozen "
                           "seeds [])"]


def test_report_section_renders_the_verdicts_and_is_left_out_without_tuned_cells(tmp_path):
    from bench.report.tuning import tuning_section
    from bench.report.context import ReportContext
    from bench.results.store import Results

    base = [1.0, 2.0, 3.0, 4.0]
    records = (_seeds("dinov2_s", base, [v - 0.5 for v in base])
               + _seeds("siglip", [v - 0.2 for v in base], [v + 0.3 for v in base]))

    def ctx(recs):
        return ReportContext(Results(tmp_path, records=recs), tmp_path / "R.md", [], [], {}, {},
                             [], n_resamples=50)

    text = tuning_section(ctx(records))
    assert "| smolvla" in text and HELPS in text and HURTS in text
    assert ("frozen siglip > dinov2_s; tuned dinov2_s > siglip (**the ranking changes**, the "
            "leader too (siglip -> dinov2_s)") in text
    assert tuning_section(ctx([r for r in records if r.kind == GRAFT])) is None


# --- the zero-learning-rate twin -------------------------------------------------------------
TWIN = next(k.name for k in CELL_KINDS.values() if k.live_encoder)


def test_the_twin_is_the_graft_on_the_live_path_bit_for_bit(tmp_path):
    """tuned_encoder_lr0 trains the projector alone with the session's frozen encoder in the loop:
    its record is the graft's measured with --features loop, bit for bit (same trained projector,
    same scores), while the graft on stored features is not; it never reuses the graft's
    projector, never packs, and runs per tunable encoder as the tuned kind does."""
    from bench.cell.packed import packable
    from bench.cell.service import run_cell

    twin = CellSpec(TWIN, "smolvla", "spatial", 0, "dinov2_s")
    assert twin.id == "smolvla-spatial-dinov2_s-tuned_encoder_lr0-seed0"
    assert twin.reference == CellSpec(GRAFT, "smolvla", "spatial", 0, "dinov2_s")
    assert not twin.spec.shares_graft_training("dinov2_s", None)
    assert cell_context(twin, "cache", projectors={}).features_mode == "loop"
    assert packable(twin) and TWIN not in PROFILES["tiny"].controls
    profile = dataclasses.replace(TINY, controls=(TWIN,), control_encoders=("pixels",))
    assert [c.id for c in control_cells(profile) if c.backbone == "pi05" and c.seed == 0] == [
        "pi05-spatial-dinov2_s-tuned_encoder_lr0-seed0"]

    graft = CellSpec(GRAFT, "smolvla", "spatial", 0, "dinov2_s")
    ws = lent_workspace(PROFILE, ResultStore(tmp_path / "twin"))
    held = {k: v.clone() for k, v in ws.encoder("dinov2_s").state_dict().items()}
    a = run_cell(twin, ws)
    assert all(torch.equal(v, ws.encoder("dinov2_s").state_dict()[k]) for k, v in held.items())
    assert a.training.trainable_params == a.training.projector_params
    assert a.measured.features_mode == "loop" and a.measured.feature_dtype is None
    live = run_cell(graft, ws, "loop")
    stored = run_cell(graft, ws, "cache")
    assert a.scores.per_window == live.scores.per_window
    assert a.training.loss_curve == live.training.loss_curve
    assert a.scores.per_window != stored.scores.per_window  # fp16 store against fp32 live


def test_no_verdict_where_the_frozen_loss_still_falls():
    """The same -0.5 on two seeds, but the frozen twin's logged loss still halves in its last
    quarter: tuning may only have trained faster, so no verdict; the change is measured."""
    falling = [[s, 1.0 / (1 + s)] for s in range(0, 100, 10)] + [[99, 0.01]]
    # quarters of 100 steps: [50, 75) holds 0.3, 0.31; [75, 100) holds 0.3, 0.3, 0.31
    assert last_quarter_change([FLAT]) == pytest.approx((0.91 / 3) / (0.61 / 2) - 1)
    assert last_quarter_change([falling]) < -0.2
    assert np.isnan(last_quarter_change([[[0, 1.0], [10, 0.5]]]))  # no third-quarter point
    base = [1.0, 2.0, 3.0, 4.0]
    records = [r.replace(loss_curve=falling) if r.kind == GRAFT else r
               for r in _seeds("dinov2_s", base, [v - 0.5 for v in base])]
    (c,) = tuned_vs_frozen(records, n_resamples=50).comparisons
    assert c.diff == pytest.approx(-0.5) and c.verdict == NOT_FLAT and not c.flattened


def test_the_twin_splits_tuned_minus_frozen_into_the_path_and_the_move():
    """frozen, twin = frozen + 0.1 everywhere (the live path hurts), tuned = frozen - 0.3 (the
    encoder's move helps by 0.4): both halves and their intervals are exact, and add up to
    tuned - frozen; without the twin there is no split."""
    base = [1.0, 2.0, 3.0, 4.0, 5.0]
    records = _seeds("dinov2_s", base, [v - 0.3 for v in base]) + [
        make_record(kind=TWIN, encoder="dinov2_s", seed=s, per_window=[v + 0.1 for v in base])
        for s in (0, 1)]
    (c,) = tuned_vs_frozen(records, n_resamples=100).comparisons
    split = c.twin
    assert split.seeds == [0, 1] and split.twin_mse == pytest.approx(3.1)
    assert split.path == pytest.approx(0.1) and split.path_ci == pytest.approx((0.1, 0.1))
    assert split.moved == pytest.approx(-0.4) and split.moved_ci == pytest.approx((-0.4, -0.4))
    assert split.path + split.moved == pytest.approx(c.diff)
    assert split.path_verdict == LIVE_HURTS and split.moved_verdict == MOVED_HELPS
    assert c.verdict == HELPS
    (alone,) = tuned_vs_frozen([r for r in records if r.kind != TWIN],
                               n_resamples=20).comparisons
    assert alone.twin is None


def test_report_section_gives_the_split_beside_the_verdict(tmp_path):
    from bench.report.context import ReportContext
    from bench.report.tuning import tuning_section
    from bench.results.store import Results

    base = [1.0, 2.0, 3.0, 4.0]
    records = _seeds("dinov2_s", base, [v - 0.3 for v in base]) + [
        make_record(kind=TWIN, encoder="dinov2_s", seed=s, per_window=[v + 0.1 for v in base])
        for s in (0, 1)]
    text = tuning_section(ReportContext(Results(tmp_path, records=records), tmp_path / "R.md",
                                        [], [], {}, {}, [], n_resamples=50))
    assert "zero-learning-rate twin" in text
    assert re.search(rf"\| 0\.1 +\| \[0\.1, 0\.1\] +\| {LIVE_HURTS} +\| -0\.4 +\| "
                     rf"\[-0\.4, -0\.4\] +\| {MOVED_HELPS} ", text)
