"""CI regression mode: known-answer checks on hand-made records, then the plugin end to end
(pytester; the session's seams give it a model-free workspace and hand-made records)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

import backbones  # noqa: F401  imported before pytester's sys.modules snapshot: the in-process
import encoders  # noqa: F401   runs then reuse them (re-importing torchvision ops would fail)
from bench.regression import baseline as B
from tests.factories import make_record

pytest_plugins = ["pytester"]


def _cell(level=0.07, encoder="dinov2_s", **kw) -> dict:
    return make_record(encoder=encoder, level=level, **kw)


# ---------------------------------------------------------------------------------------------
# Specs


@pytest.mark.parametrize("spec, metric, limit, relative, paired", [
    ("mse:10%", "mse", 0.10, True, False),
    ("raw_mse:7.5%", "raw_mse", 0.075, True, False),
    ("mse:0.002", "mse", 0.002, False, False),
    ("mse:10%:paired", "mse", 0.10, True, True),
    ("raw_mse:1e-3:paired", "raw_mse", 0.001, False, True),
])
def test_parse_threshold_specs(spec, metric, limit, relative, paired):
    check = B.parse_compare_fail(spec)
    assert (check.metric, check.relative, check.paired, check.scope) == (metric, relative, paired, "cell")
    assert check.limit == pytest.approx(limit)


def test_parse_rank_spec():
    assert B.parse_compare_fail("rank").scope == "group"


@pytest.mark.parametrize("spec", ["mse", "mean:5%", "mse:-1%", "mse:10%:unpaired", "rank:1", ""])
def test_bad_spec_names_itself_and_valid_forms(spec):
    with pytest.raises(B.BaselineError) as err:
        B.parse_compare_fail(spec)
    assert repr(spec) in str(err.value) and B.VALID_FORMS in str(err.value)


# ---------------------------------------------------------------------------------------------
# Threshold checks (known answers)


def test_plus_16_percent_fails_mse_10_percent_with_one_line_message():
    base, now = _cell(0.07), _cell(0.0812)
    message = B.parse_compare_fail("mse:10%").fails(base, now)
    assert message == ("smolvla-spatial-dinov2_s-seed0: mse 0.0812 vs baseline 0.07 (+16.0%) "
                       "exceeds mse:10%")


def test_plus_5_percent_passes_mse_10_percent():
    assert B.parse_compare_fail("mse:10%").fails(_cell(0.07), _cell(0.0735)) is None


def test_raw_and_absolute_thresholds():
    base, now = _cell(0.07), _cell(0.073)  # +0.003 normalised, +0.006 raw (raw_scale 2)
    assert B.parse_compare_fail("mse:0.002").fails(base, now)
    assert B.parse_compare_fail("mse:0.004").fails(base, now) is None
    assert B.parse_compare_fail("raw_mse:0.005").fails(base, now).startswith(
        "smolvla-spatial-dinov2_s-seed0: raw_mse 0.146 vs baseline 0.14 ")


def test_paired_rule_ignores_a_big_shift_drowned_in_window_noise():
    base = _cell(per_window=[2.0] * 24)
    # +20% on average, but each window moves by +0.4 +/- 1.8: the paired interval contains 0.
    now = _cell(per_window=[2.4 + (1.8 if i % 2 else -1.8) for i in range(24)])
    assert B.parse_compare_fail("mse:10%").fails(base, now)
    assert B.parse_compare_fail("mse:10%:paired").fails(base, now) is None


def test_paired_rule_fails_a_consistent_shift():
    base = _cell(per_window=[2.0] * 24)
    now = _cell(per_window=[2.4 + (0.01 if i % 2 else -0.01) for i in range(24)])
    message = B.parse_compare_fail("mse:10%:paired").fails(base, now)
    assert message.startswith("smolvla-spatial-dinov2_s-seed0: mse 2.4 vs baseline 2 (+20.0%) "
                              "exceeds mse:10%:paired (paired 95% CI of now - baseline [+0.39")


def test_paired_interval_is_deterministic_and_pairs_by_window_id():
    a, b = _cell(0.08, noise=0.01), _cell(0.07, noise=0.01)
    assert B.paired_interval(*B.aligned(a, b, "normalized")) == \
        B.paired_interval(*B.aligned(a, b, "normalized"))
    shuffled = b.replace(window_ids=b.scores.window_ids[::-1],
                         per_window={k: v[::-1] for k, v in b.scores.per_window.items()})
    assert np.allclose(B.aligned(a, shuffled, "raw")[1], B.aligned(a, b, "raw")[1])


def test_the_paired_interval_draws_episodes_and_the_baseline_file_keeps_them():
    """Known answer: now - baseline is +0.3 on every window of two episodes and -0.1 on every
    window of two others (8 windows each; +0.1 on average): drawn by episode the interval holds
    0, drawn as 32 independent windows it would not. The baseline file's cell keeps the window
    episodes, so a rank check on two baseline cells draws them too."""
    from bench.results.record import from_snapshot, snapshot_json

    episode = [i // 8 for i in range(32)]
    shift = [0.3, -0.1, 0.3, -0.1]
    base = _cell(0.5, n_tasks=1, n_windows=32, window_episode=episode)
    now = _cell(n_tasks=1, window_episode=episode, per_window=[
        v + shift[e] for v, e in zip(base.scores.per_window["normalized"], episode)])
    d, lo, hi = B.paired_interval(*B.aligned(now, base, "normalized"))
    assert d == pytest.approx(0.1) and lo < 0 < d < hi, (d, lo, hi)
    plain = [r.replace(window_episode=None) for r in (now, base)]
    _, w_lo, _ = B.paired_interval(*B.aligned(*plain, "normalized"))
    assert w_lo > 0
    kept = from_snapshot(json.loads(json.dumps(snapshot_json(base))))
    assert kept.scores.window_episode == episode
    assert B.paired_interval(*B.aligned(now, kept, "normalized")) == (d, lo, hi)
    assert B.paired_interval(*B.aligned(kept, now, "normalized"))[1:] == (-hi, -lo)


# ---------------------------------------------------------------------------------------------
# Rank check (tie band = paired 95% interval containing 0)


def _group(levels: dict[str, float]) -> dict[str, dict]:
    return {e: _cell(level, encoder=e) for e, level in levels.items()}


def test_rank_flip_beyond_the_tie_band_fails():
    base = _group({"siglip": 0.0706, "dinov2_s": 0.0734})
    now = _group({"siglip": 0.0734, "dinov2_s": 0.0706})
    message = B.RankCheck().fails(base, now)
    assert message.startswith("rank flip: baseline siglip < dinov2_s by 0.0028 [")
    assert "now dinov2_s < siglip by 0.0028" in message


def test_rank_swap_within_the_tie_band_passes():
    base = _group({"siglip": 0.0706, "dinov2_s": 0.0734})
    wobble = [0.0725 + (0.01 if i % 2 else -0.01) for i in range(24)]
    now = {"siglip": _cell(encoder="siglip", per_window=wobble),
           "dinov2_s": _cell(encoder="dinov2_s", per_window=[0.0720] * 24)}
    assert now["siglip"].scores.mse["normalized"] > now["dinov2_s"].scores.mse["normalized"]  # swapped
    assert B.RankCheck().fails(base, now) is None


def test_compare_run_groups_graft_cells_by_backbone_suite_seed():
    base = [_cell(0.0706, encoder="siglip"), _cell(0.0734, encoder="dinov2_s"),
            _cell(0.05, kind="native")]
    now = [_cell(0.0734, encoder="siglip"), _cell(0.0706, encoder="dinov2_s"),
           _cell(0.05, kind="native")]
    baseline = B.snapshot(base, "ci", created="t", git_commit="c", machine={})
    comp = B.compare_run("ci", baseline, [r.cell_id for r in now],
                         {r.cell_id: r for r in now}, [B.parse_compare_fail("rank")])
    assert comp.groups_compared == 1 and list(comp.flips) == ["smolvla-spatial-seed0"]
    assert not comp.regressed and comp.failed


# ---------------------------------------------------------------------------------------------
# Baseline files and provenance


def test_snapshot_round_trip_and_new_and_not_compared(tmp_path):
    records = [_cell(0.07, encoder="siglip"), _cell(0.08, encoder="dinov2_s")]
    path = tmp_path / "ci.json"
    path.write_text(json.dumps(B.snapshot(records, "ci", created="t", git_commit="c",
                                          machine={"node": "n"}).to_json()))
    baseline = B.load_baseline(path)
    assert baseline.protocol_hash == records[0].measured.protocol_hash
    fresh = _cell(0.09, encoder="repvit")
    now = {r.cell_id: r for r in (records[0], fresh)}
    comp = B.compare_run("ci", baseline, list(now), now, [B.parse_compare_fail("mse:10%")])
    assert [r.verdict for r in comp.rows] == ["ok"]
    assert comp.new == ["smolvla-spatial-repvit-seed0"]
    assert comp.not_compared == ["smolvla-spatial-dinov2_s-seed0 (not run)"]
    section = B.markdown_section(comp, path)
    assert "New (not in the baseline, passed): smolvla-spatial-repvit-seed0." in section
    assert "Not compared: smolvla-spatial-dinov2_s-seed0 (not run)." in section


@pytest.mark.parametrize("content, words", [
    (None, "not found"),
    ("{not json", "is unreadable (Expecting property name"),
    ('{"schema": 1}', "is not a schema-1 graftbench baseline"),
    ('{"schema": 1, "cells": {"x": {"mse": {}}}}', "cell 'x' lacks"),
])
def test_missing_or_corrupt_baseline_is_one_line_naming_the_file(tmp_path, content, words):
    path = tmp_path / "ci.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises(B.BaselineError) as err:
        B.load_baseline(path)
    assert str(path) in str(err.value) and words in str(err.value)
    assert "\n" not in str(err.value)


def test_protocol_and_version_mismatch_are_named():
    base, now = _cell(), _cell()
    now = now.replace(protocol_hash="abc123", versions={**now.run.versions, "torch": "9.9"})
    assert B.provenance_mismatch(base, {}, now) == [
        f"protocol_hash abc123 (baseline {base.measured.protocol_hash})",
        "torch 9.9 (baseline 2.11.0)",
    ]
    assert B.provenance_mismatch(base, {}, _cell()) == []


def test_another_normaliser_is_a_mismatch_never_compared():
    def with_norm(fingerprint):
        return _cell(checkpoint={"repo_id": "lerobot/pi05_base", "revision": "b" * 40,
                                 "normalizer": "dataset:spatial",
                                 "normalizer_fingerprint": fingerprint})

    base = with_norm("aaaaaaaaaaaa")
    assert B.provenance_mismatch(base, {}, with_norm("aaaaaaaaaaaa")) == []
    assert B.provenance_mismatch(base, {}, with_norm("bbbbbbbbbbbb")) == [
        "normalizer bbbbbbbbbbbb (baseline aaaaaaaaaaaa)"]
    assert B.provenance_mismatch(base, {}, _cell()) == ["normalizer None (baseline aaaaaaaaaaaa)"]


def test_baseline_names():
    assert B.baseline_path(B.Path("d"), "ci-main") == B.Path("d/ci-main.json")
    assert B.baseline_path(B.Path("d"), "x/y.json") == B.Path("x/y.json")
    with pytest.raises(B.BaselineError, match="baseline name"):
        B.baseline_path(B.Path("d"), "a b")


def test_degrade_features_blinds_a_fraction_of_the_given_frames():
    import torch

    from bench.regression.run import degrade_features

    x = torch.arange(24.0).reshape(6, 2, 2)
    full = degrade_features({"cam": x}, 1.0, [1, 3])["cam"]
    assert torch.equal(full[[1, 3]], torch.ones(2, 2, 2))
    assert torch.equal(full[[0, 2, 4, 5]], x[[0, 2, 4, 5]])
    half = degrade_features({"cam": x}, 0.5, [1, 3])["cam"]
    assert sum(torch.equal(half[i], torch.ones(2, 2)) for i in range(6)) == 1
    assert torch.equal(x, torch.arange(24.0).reshape(6, 2, 2))  # input untouched
    # Per batch (the feature store applies it to each batch read): rows name the global frames.
    rows = torch.tensor([3, 0, 3, 5])
    batch = degrade_features({"cam": x[rows]}, 0.5, [1, 3], rows=rows)["cam"]
    assert torch.equal(batch, half[rows])


# ---------------------------------------------------------------------------------------------
# End to end: the plugins in a pytester session whose cells write hand-made records

CONFTEST = '''
import json
import types
from pathlib import Path

import pytest

from bench.plugin import SESSION_KEY
from bench.progress import QUIET
from bench.cell.plan import CellResult
from tests.factories import make_record

pytest_plugins = ["bench.plugin"]


@pytest.hookimpl(trylast=True)
def pytest_configure(config):
    """The session's seams: a workspace with no models, a cell runner writing hand-made records
    (marked with an installed feature transform, as bench.cell.runner marks them), and a report
    builder that keeps the sections it is handed (REPORT.md itself: bench.report.build's tests)."""
    gs = config.stash[SESSION_KEY]
    levels = json.loads(Path("levels.json").read_text())
    transforms = set()

    def fake_runner(cell, ws, context):
        record = make_record(kind=cell.kind, backbone=cell.backbone, suite=cell.suite,
                             encoder=cell.encoder, seed=cell.seed, variant=cell.variant,
                             level=levels.get(cell.id, 0.05))
        if context.feature_transform is not None:
            transforms.add(cell.encoder)
            record = record.replace(feature_transform=context.feature_transform.description)
        gs.store.write(record)
        return CellResult(record)

    def keep_sections(results_dir, path, extra_sections=()):
        Path("out.json").write_text(json.dumps({
            "sections": list(extra_sections), "transforms": sorted(transforms)}))

    gs.use_seams(workspace_factory=lambda session: types.SimpleNamespace(progress=QUIET),
                 cell_runner=fake_runner, report_builder=keep_sections)
'''

GRID = '''
def test_graft(graft_cell, graft_session):
    graft_session.run(graft_cell)


def test_control(control_cell, graft_session):
    graft_session.run(control_cell)
'''

LEVELS = {"smolvla-spatial-siglip-seed0": 0.0706, "smolvla-spatial-dinov2_s-seed0": 0.0734,
          "smolvla-spatial-fastvit-seed0": 0.0800}
SIGLIP = "smolvla-spatial-siglip-seed0"


@pytest.fixture
def grid(pytester):
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(test_grid=GRID)
    pytester.path.joinpath("levels.json").write_text(json.dumps(LEVELS))

    def run(*args, encoders="siglip,dinov2_s,fastvit", levels=None):
        if levels is not None:
            pytester.path.joinpath("levels.json").write_text(json.dumps(levels))
        return pytester.runpytest(  # --rerun: every run measures (the fake cells, new levels)
            "-p", "no:cacheprovider", "-W", "ignore::pytest.PytestAssertRewriteWarning", "--rerun",
            "--backbones", "smolvla", "--suites", "spatial",
            "--seeds", "0", "--controls", "native", "--encoders", encoders,
            "--results-dir", str(pytester.path / "results"), "--report",
            str(pytester.path / "REPORT.md"), "--baseline-dir", str(pytester.path / "bl"), *args)

    run.path = pytester.path
    return run


def _section(path) -> tuple[str, str]:
    (title, body), = json.loads((path / "out.json").read_text())["sections"]
    return title, body


def test_save_then_compare_same_records_passes(grid):
    saved = grid("--save-baseline", "ci")
    saved.assert_outcomes(passed=4)
    data = json.loads((grid.path / "bl" / "ci.json").read_text())
    assert sorted(data["cells"]) == sorted([*LEVELS, "smolvla-spatial-native-seed0"])
    assert data["protocol_hash"] and data["versions"] and data["git_commit"] and data["machine"]
    assert set(data["cells"][SIGLIP]["per_window"]) == {"normalized", "raw"}
    result = grid("--compare", "ci", "--compare-fail", "mse:10%", "--compare-fail", "rank")
    result.assert_outcomes(passed=4)
    assert result.ret == 0
    result.stdout.fnmatch_lines(["*against ci (*ci.json): 4 compared, 0 regressed, 0 rank flip(s)*"])
    title, body = _section(grid.path)
    assert title == "Against baseline ci" and "| ok |" in body and "REGRESSED" not in body


def test_lowered_baseline_fails_exactly_that_cell(grid):
    grid("--save-baseline", "ci").assert_outcomes(passed=4)
    path = grid.path / "bl" / "ci.json"
    data = json.loads(path.read_text())
    cell = data["cells"][SIGLIP]
    cell["mse"] = {k: v * 0.8 for k, v in cell["mse"].items()}
    cell["per_window"] = {k: [x * 0.8 for x in v] for k, v in cell["per_window"].items()}
    path.write_text(json.dumps(data))
    result = grid("--compare", "ci", "--compare-fail", "mse:10%")
    result.assert_outcomes(passed=3, failed=1)
    result.stdout.fnmatch_lines([  # the failure is the one-line message, no traceback
        f"_* test_graft[[]{SIGLIP}] _*",
        f"{SIGLIP}: mse 0.0706 vs baseline 0.05648 (+25.0%) exceeds mse:10%",
        "-* graftbench baseline -*"])
    assert "| REGRESSED" not in _section(grid.path)[1]  # the verdict column holds the message
    assert f"{SIGLIP}: mse 0.0706 vs baseline 0.05648 (+25.0%) exceeds mse:10% |" in \
        _section(grid.path)[1]


def test_new_and_not_compared_are_listed(grid):
    grid("--save-baseline", "ci").assert_outcomes(passed=4)
    result = grid("--compare", "ci", "--compare-fail", "mse:10%", encoders="siglip,repvit")
    result.assert_outcomes(passed=3)
    result.stdout.fnmatch_lines(["new (not in baseline): smolvla-spatial-repvit-seed0",
                                 "not compared: smolvla-spatial-dinov2_s-seed0 (not run), "
                                 "smolvla-spatial-fastvit-seed0 (not run)"])
    body = _section(grid.path)[1]
    assert "New (not in the baseline, passed): smolvla-spatial-repvit-seed0." in body
    assert "smolvla-spatial-fastvit-seed0 (not run)" in body


def test_rank_flip_fails_the_session(grid):
    grid("--save-baseline", "ci").assert_outcomes(passed=4)
    flipped = {**LEVELS, SIGLIP: 0.0734, "smolvla-spatial-dinov2_s-seed0": 0.0706}
    result = grid("--compare", "ci", "--compare-fail", "rank", levels=flipped)
    result.assert_outcomes(passed=4)
    assert result.ret == pytest.ExitCode.TESTS_FAILED
    result.stdout.fnmatch_lines(["RANK FLIP smolvla-spatial-seed0: rank flip: baseline siglip < "
                                 "dinov2_s by 0.0028 *, now dinov2_s < siglip by 0.0028 *"])
    assert "1 flip(s)" in _section(grid.path)[1]


def test_protocol_mismatch_warns_and_strict_refuses(grid):
    grid("--save-baseline", "ci").assert_outcomes(passed=4)
    path = grid.path / "bl" / "ci.json"
    data = json.loads(path.read_text())
    for cell in data["cells"].values():
        cell["protocol_hash"] = "0ld0ld0ld0ld"
    path.write_text(json.dumps(data))
    result = grid("--compare", "ci", "--compare-fail", "mse:10%")
    result.assert_outcomes(passed=4, warnings=1)
    result.stdout.fnmatch_lines(["*BaselineMismatchWarning: baseline ci: * measured with "
                                 "protocol_hash * (baseline 0ld0ld0ld0ld)*"])
    assert "Measured differently from the baseline" in _section(grid.path)[1]
    strict = grid("--compare", "ci", "--compare-strict")
    strict.assert_outcomes(passed=0, failed=4)
    strict.stdout.fnmatch_lines(["*: not compared with baseline ci: protocol_hash * (--compare-strict)"])
    data["protocol_hashes"] = ["0ld0ld0ld0ld"]
    path.write_text(json.dumps(data))
    refused = grid("--compare", "ci", "--compare-strict")
    assert refused.ret == pytest.ExitCode.USAGE_ERROR
    refused.stderr.fnmatch_lines(["ERROR: --compare-strict: this run's protocol * differs from *"])


@pytest.mark.parametrize("args, message", [
    (["--compare", "nope"], "ERROR: baseline file */bl/nope.json not found; save one with *"),
    (["--compare-fail", "mse:10%"], "ERROR: --compare-fail / --compare-strict need --compare NAME"),
    (["--save-baseline", "x", "--compare", "x.json", "--compare-fail", "mse:ten%"],
     "ERROR: --compare-fail 'mse:ten%' not understood; valid forms: mse:10%, *"),
    (["--degrade-encoder", "siglip:2"], "ERROR: --degrade-encoder 'siglip:2': expected NAME:FACTOR*"),
    (["--degrade-encoder", "siglip:1", "--save-baseline", "x"], "ERROR: --degrade-encoder plants*"),
])
def test_misuse_is_a_one_line_usage_error(grid, args, message):
    result = grid(*args)
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines([message])


def test_help_lists_the_options(grid):
    result = grid("--help")
    assert result.ret == 0
    result.stdout.fnmatch_lines(["*--compare-fail=SPEC*", "*mse:0.002 (absolute), mse:10%:paired, rank*"])


def test_degrade_encoder_installs_its_feature_transform(grid):
    grid("--degrade-encoder", "siglip:1.0").assert_outcomes(passed=4)
    assert json.loads((grid.path / "out.json").read_text())["transforms"] == ["siglip"]
    record = json.loads((grid.path / "results" / "cells" / f"{SIGLIP}.json").read_text())
    assert record["feature_transform"] == "degraded siglip:1.0"
