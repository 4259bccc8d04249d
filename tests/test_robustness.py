"""The robustness tier: the perturbation table, its known answers on the tiny world,
its bad input, and `pytest bench --robustness` end to end.

Known answers: `blind` degrades by exactly 0 under every perturbation; severity 0 gives the
clean record's bits (graft, native tower through the wrapper, native); the planted invariance:
`pixels_ones_norm` does not move under brightness or contrast while `pixels_ones` does, and under
a dimmer scene pixels_ones (on all 148 held-out windows) and the released policy (whose tower has
no such invariance) degrade by a paired interval while pixels_ones_norm does not. Cells train a few steps: no answer here reads a training margin.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from bench.analysis.robustness import robustness_table
from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY, with_overrides
from bench.robust.perturbations import PERTURBATIONS, Applied, parse_robustness
from bench.robust.rescore import RobustUnavailable, measure_robust
from bench.cell.service import run_cell

FEW_STEPS = with_overrides(TINY, steps=12)
BACKBONE = "smolvla"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A 12-step tiny world with its own results store, and the cells measured in it."""
    from bench.results.store import ResultStore
    from tests.worlds import lent_workspace

    ws = lent_workspace(FEW_STEPS, ResultStore(tmp_path_factory.mktemp("robust")))
    records = {}

    def cell(kind, encoder=None):
        spec = CellSpec(kind, BACKBONE, "spatial", 0, encoder)
        if spec.id not in records:
            records[spec.id] = run_cell(spec, ws)
        return spec, records[spec.id]

    return ws, cell


def clean_on(record, robust) -> np.ndarray:
    """The cell record's normalised per-window errors on the robustness record's windows."""
    position = {w: i for i, w in enumerate(record.scores.window_ids)}
    return np.asarray(record.scores.per_window["normalized"])[[position[w]
                                                              for w in robust.window_ids]]


def test_parse_names_kinds_and_severities_and_refuses_the_rest():
    assert len(parse_robustness(["all"], "x")) == 3 * len(PERTURBATIONS)
    assert [a.label for a in parse_robustness(["blur:3,1", "brightness"], "x")] == [
        "brightness:1", "brightness:2", "brightness:3", "blur:1", "blur:3"]
    with pytest.raises(ValueError, match=r"--robustness: unknown perturbation kind 'fog'; "
                                         r"valid kinds: brightness, .*occlusion"):
        parse_robustness(["fog"], "--robustness")
    with pytest.raises(ValueError, match=r"severity 4 out of range; give severities in 0..3"):
        parse_robustness(["noise:4"], "--robustness")


def test_each_kind_is_the_identity_at_zero_and_a_fixed_draw_per_window():
    images = {"cam": torch.rand(3, 3, 64, 64)}
    frames = torch.tensor([5, 9, 12])
    for kind in PERTURBATIONS:
        assert Applied(kind, 0).images(images, frames) is images
        moved = Applied(kind, 3).images(images, frames)["cam"]
        assert not torch.equal(moved, images["cam"]), kind
        assert moved.min() >= 0 and moved.max() <= 1
        # window 9 alone gets the same frame as in the batch: the draw is the window's own
        alone = Applied(kind, 3).images({"cam": images["cam"][1:2]}, frames[1:2])["cam"]
        torch.testing.assert_close(alone[0], moved[1], rtol=0, atol=1e-6)
    assert Applied("blur", 2).to_json()["params"] == {"sigma_frac": 0.01}


def test_blind_degrades_by_exactly_zero_and_severity_zero_gives_the_clean_bits(world):
    ws, cell = world
    everything = parse_robustness(["all", "brightness:0"], "test")
    spec, record = cell("graft", "blind")
    robust, measured = measure_robust(spec, ws, everything)
    assert measured and len(robust.entries) == len(everything)
    clean = clean_on(record, robust)
    for entry in robust.entries:  # blind's features ignore the image: the very same bits
        assert entry.per_window["normalized"] == clean.tolist(), entry.perturbation
    for kind in ("graft", "native_wrapped", "native"):
        spec, record = cell(kind, "pixels" if kind == "graft" else None)
        robust, _ = measure_robust(spec, ws, parse_robustness(["brightness:0"], "test"))
        assert robust.entries[0].per_window["normalized"] == clean_on(record, robust).tolist()
    again, measured = measure_robust(CellSpec("graft", BACKBONE, "spatial", 0, "blind"), ws,
                                     everything)
    assert not measured and again.entries == robust_entries(ws, "blind")


def robust_entries(ws, encoder):
    from bench.results.robust import load_robust

    return load_robust(ws.store.root, f"{BACKBONE}-spatial-{encoder}-seed0").entries


def test_planted_invariance_holds_and_the_released_tower_degrades(world):
    ws, cell = world
    lighting = parse_robustness(["brightness", "contrast"], "test")
    moved = {}
    for encoder in ("pixels_ones", "pixels_ones_norm"):
        spec, record = cell("graft", encoder)
        robust, _ = measure_robust(spec, ws, lighting)
        clean = clean_on(record, robust)
        moved[encoder] = max(np.abs(np.asarray(e.per_window["normalized"]) - clean).max()
                             / clean.mean() for e in robust.entries)
    assert moved["pixels_ones_norm"] < 1e-4 < 0.01 < moved["pixels_ones"], moved
    # By the paired interval over held-out episodes (16, then their windows: 148): the twin's
    # degradation is nil. pixels_ones' is not separated from 0: the barely trained projector
    # moves each episode's error either way (+3.7% on average; drawn as independent windows it
    # read [+0.7%, +6.8%], a precision the 16 episodes do not have).
    dim = parse_robustness(["brightness:3"], "test")
    pairs = [(cell("graft", e)[1], measure_robust(cell("graft", e)[0], ws, dim, window_stride=1)[0])
             for e in ("pixels_ones", "pixels_ones_norm")]
    table = robustness_table([r for r, _ in pairs], [rr for _, rr in pairs], BACKBONE, "spatial",
                             n_resamples=1000)
    assert table.n_episodes == 16 and table.n_windows == 148
    low, high = table.cells[("pixels_ones", "brightness:3")].ci
    assert low < 0.0 < 0.03 < table.cells[("pixels_ones", "brightness:3")].relative < high
    low, high = table.cells[("pixels_ones_norm", "brightness:3")].ci
    assert -1e-5 < low <= 0 <= high < 1e-5, (low, high)
    spec, native = cell("native")
    robust, _ = measure_robust(spec, ws, lighting)
    from bench.results.robust import load_all_robust

    table = robustness_table([native], load_all_robust(ws.store.root)[0], BACKBONE, "spatial",
                             n_resamples=500)
    degradation = table.cells[("native", "brightness:3")]
    assert degradation.ci[0] > 0.05, degradation  # a dimmer scene: worse, by a paired interval


def test_the_intervals_draw_held_out_episodes_not_windows():
    """Known answer on stand-ins: a perturbation that moves every window of an episode alike,
    by +50% or -20% from episode to episode within each task (+15% on average, 8 episodes of 8
    windows). Drawn as 64 independent windows the interval would exclude 0; drawn by episode
    (what varies from one held-out demonstration to the next) it does not. A second release
    of the same cells is drawn too (its own column, not another seed's)."""
    from bench.results.robust import RobustEntry, RobustRecord, base_of
    from tests.factories import make_record

    episode = [i % 2 + 2 * (i // 16) for i in range(64)]  # 8 episodes, task = episode % 2
    gain = {0: 0.5, 2: -0.2, 4: 0.5, 6: -0.2, 1: -0.2, 3: 0.5, 5: -0.2, 7: 0.5}

    def table_of(episodes):
        records, robust = [], []
        for release in (0, 1):
            record = make_record(encoder="dinov2_s", level=1.0, n_windows=64, release=release,
                                 window_episode=episodes, cell_id="smolvla-spatial-dinov2_s-"
                                 + ("rel1-" if release else "") + "seed0")
            clean = np.asarray(record.scores.per_window["normalized"])
            perturbed = clean * (1 + np.array([gain[e] for e in episode]))
            entries = [RobustEntry({"kind": "blur", "severity": 2, "params": {}},
                                   {"normalized": float(perturbed.mean())},
                                   {"normalized": perturbed.tolist()})]
            records.append(record)
            robust.append(RobustRecord(record.cell_id, "graft", BACKBONE, "spatial", "dinov2_s",
                                       0, base_of(record), record.scores.window_ids, entries))
        return robustness_table(records, robust, BACKBONE, "spatial", n_resamples=1000)

    by_episode = table_of(episode)
    assert by_episode.releases == [0, 1] and by_episode.n_episodes == 8
    cell = by_episode.cells[("dinov2_s", "blur:2")]
    assert cell.relative == pytest.approx(0.15 * 1.0, rel=0.2)  # the ramp weights the gains
    assert cell.ci[0] < 0 < cell.relative < cell.ci[1], cell
    by_window = table_of(None).cells[("dinov2_s", "blur:2")]
    assert by_window.relative == cell.relative and by_window.ci[0] > 0, by_window


def test_the_ranking_leads_with_perturbed_mse_so_blind_does_not_lead_when_it_predicts_worst():
    """Known answer on stored-record stand-ins (tests/factories.py: per-window MSE = level x a
    ramp averaging 1): blind 2.0 clean and perturbed (degrades by 0, predicts worst); dinov2_s
    1.0 -> 1.2 (+20%); siglip 1.0 -> 1.5 (+50%). Perturbed MSE ranks dinov2_s, siglip, blind;
    the degradation, kept beside it, ranks blind first."""
    from bench.report.robustness import _ranking_text
    from bench.results.robust import RobustEntry, RobustRecord, base_of
    from tests.factories import make_record

    levels = {"blind": (2.0, 2.0), "dinov2_s": (1.0, 1.2), "siglip": (1.0, 1.5)}
    records, robust = [], []
    for encoder, (clean, perturbed) in levels.items():
        for seed in (0, 1):
            record = make_record(encoder=encoder, seed=seed, level=clean)
            ramp = np.asarray(record.scores.per_window["normalized"]) / clean
            entries = [RobustEntry({"kind": kind, "severity": 2, "params": {}},
                                   {"normalized": perturbed},
                                   {"normalized": (perturbed * ramp).tolist()})
                       for kind in ("blur", "noise")]
            records.append(record)
            robust.append(RobustRecord(record.cell_id, "graft", BACKBONE, "spatial", encoder,
                                       seed, base_of(record), record.scores.window_ids, entries))
    table = robustness_table(records, robust, BACKBONE, "spatial", n_resamples=200)
    assert [(name, round(mse, 9), tie) for name, mse, _, tie in table.ranking] == [
        ("dinov2_s", 1.2, True), ("siglip", 1.5, False), ("blind", 2.0, False)]
    assert table.most_robust == "dinov2_s" and table.least_degraded == "blind"
    assert [(name, round(d, 9)) for name, d, _, _ in table.degradation_ranking] == [
        ("blind", 0.0), ("dinov2_s", 0.2), ("siglip", 0.5)]
    text = _ranking_text(table)
    assert "**dinov2_s** predicts best under perturbation" in text
    assert "| 3      | blind" in text and "(least degraded here: blind)" in text


def test_a_cell_without_record_or_projector_names_the_command(world, tmp_path):
    ws, cell = world
    missing = CellSpec("graft", BACKBONE, "spatial", 5, "pixels")
    with pytest.raises(RobustUnavailable, match=r"no stored record .* pytest bench -k "
                                                r"\"test_graft and smolvla-spatial-pixels-seed5\""):
        measure_robust(missing, ws, parse_robustness(["blur:1"], "t"))
    spec, record = cell("graft", "pixels")
    first, _ = measure_robust(spec, ws, parse_robustness(["blur:1"], "t"))
    (ws.store.root / record.training.projector_file).rename(tmp_path / "kept.safetensors")
    try:
        # A complete case resumes without its projector (a committed study keeps none) ...
        again, measured = measure_robust(spec, ws, parse_robustness(["blur:1"], "t"))
        assert not measured and again.entries == first.entries
        # ... and one with something left to score names the command that keeps it.
        with pytest.raises(RobustUnavailable, match=r"no stored projector.*is missing: run the "
                                                    r"cell again .*pytest bench -k"):
            measure_robust(spec, ws, parse_robustness(["blur:2"], "t"))
    finally:
        (tmp_path / "kept.safetensors").rename(ws.store.root / record.training.projector_file)


def test_bad_perturbations_stop_at_start_up_in_one_line(bench_cli, tmp_path):
    for args, line in ((["--robustness", "fog"], "unknown perturbation kind 'fog'"),
                       (["--robustness", "blur:1,5"], "severity 5 out of range")):
        out = bench_cli(tmp_path, *args)
        assert out.returncode == pytest.ExitCode.USAGE_ERROR, out.stdout + out.stderr
        assert f"ERROR: --robustness {args[1]}: " in out.stderr and line in out.stderr
    study = tmp_path / "study.toml"
    study.write_text('robustness = ["noise:9"]\n')
    out = bench_cli(tmp_path, "--grid", str(study))
    assert out.returncode == pytest.ExitCode.USAGE_ERROR
    assert f"{study}: robustness: 'noise:9': severity 9 out of range" in out.stderr


def test_robust_cases_run_resume_and_report(bench_cli, tmp_path):
    args = ["--backbones", BACKBONE, "--suites", "spatial", "--encoders", "blind",
            "--seeds", "0", "--controls", "native", "--steps", "3", "--robustness", "occlusion:2"]
    first = bench_cli(tmp_path, *args, "-v")
    assert first.returncode == 0, first.stdout[-3000:]
    assert "test_robust[smolvla-spatial-blind-seed0] PASSED" in first.stdout
    assert "test_robust[smolvla-spatial-native-seed0] PASSED" in first.stdout
    stored = json.loads((tmp_path / "results/robust/smolvla-spatial-blind-seed0.json").read_text())
    assert stored["entries"][0]["perturbation"]["params"] == {"side_frac": 0.25, "grey": 0.5}
    report = (tmp_path / "REPORT.md").read_text()
    assert "## Robustness" in report and "occlusion:2" in report
    again = bench_cli(tmp_path, *args, "-k", "test_robust")
    assert again.returncode == 0 and "2 passed" in again.stdout
    off = bench_cli(tmp_path, *args[:-2], "--co", "-q")
    assert "::test_robust[" not in off.stdout and "2 tests collected" in off.stdout


def test_one_pass_gives_each_perturbation_the_bits_it_gets_alone(world):
    """A case scores all its perturbations in one pass of repeated windows (bench.robust.rescore:
    full sampler batches); each entry must be what that perturbation alone gives."""
    ws, cell = world
    labels = ["brightness:3", "noise:2", "brightness:0", "occlusion:1"]
    for spec, _ in (cell("graft", "pixels_ones"), cell("native")):  # features, then images
        together, _ = measure_robust(spec, ws, parse_robustness(labels, "t"), rerun=True)
        for entry in together.entries:
            label = f"{entry.kind}:{entry.severity}"
            alone, _ = measure_robust(spec, ws, parse_robustness([label], "t"), rerun=True)
            assert alone.entries[0].per_window == entry.per_window, (spec.id, label)
            assert alone.entries[0].mse == entry.mse, (spec.id, label)
