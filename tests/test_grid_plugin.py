"""The user's interface, end to end: `pytest bench ...` with options (in this process:
tests/bench_inprocess.py)."""

from __future__ import annotations

import json

SLICE = ["--backbones", "pi05", "--suites", "spatial", "--encoders", "pixels,blind",
         "--seeds", "0", "--controls", "native", "--steps", "5"]


def test_slice_runs_resumes_and_reports(bench_cli, tmp_path):
    first = bench_cli(tmp_path, *SLICE, "-k", "pixels or native")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    assert "2 passed, 1 deselected" in first.stdout
    assert "measured 2, resumed from store 0" in first.stdout  # -k kept pixels + native only
    cells = sorted(p.name for p in (tmp_path / "results" / "cells").iterdir())
    assert cells == ["pi05-spatial-native-seed0.json", "pi05-spatial-pixels-seed0.json"]
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "results" / "cells").iterdir()}
    assert (tmp_path / "REPORT.md").exists()

    again = bench_cli(tmp_path, *SLICE, "-k", "pixels or native")
    assert again.returncode == 0, again.stdout[-3000:]
    assert "measured 0, resumed from store 2" in again.stdout  # a finished grid recomputes nothing
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps

    record = json.loads((tmp_path / "results" / "cells" / "pi05-spatial-pixels-seed0.json").read_text())
    assert record["protocol"]["steps"] == 5 and record["profile"] == "tiny"
    grid_json = tmp_path / "results" / "grid.json"
    assert sorted(json.loads(grid_json.read_text())["expected"]) == [
        "pi05-spatial-native-seed0", "pi05-spatial-pixels-seed0"]
    # Another slice adds its cells to what the folder expects; the whole grid redefines it.
    third = bench_cli(tmp_path, *SLICE, "-k", "blind")
    assert third.returncode == 0 and "measured 1, resumed from store 0" in third.stdout
    expected = json.loads(grid_json.read_text())["expected"]
    assert sorted(expected) == ["pi05-spatial-blind-seed0", "pi05-spatial-native-seed0",
                                "pi05-spatial-pixels-seed0"]
    grid_json.write_text(json.dumps({"expected": expected + ["pi05-spatial-gone-seed0"],
                                     "profile": "tiny"}))
    whole = bench_cli(tmp_path, *SLICE)
    assert whole.returncode == 0 and "measured 0, resumed from store 3" in whole.stdout
    assert sorted(json.loads(grid_json.read_text())["expected"]) == sorted(expected)


def test_unknown_names_fail_before_any_work_listing_valid_ones(bench_cli, tmp_path):
    bad_encoder = bench_cli(tmp_path, "--encoders", "dinov3", "--controls", "none")
    assert bad_encoder.returncode != 0
    assert "unknown encoder" in (bad_encoder.stdout + bad_encoder.stderr).lower()
    assert "dinov2_s" in bad_encoder.stdout + bad_encoder.stderr
    bad_backbone = bench_cli(tmp_path, "--backbones", "smolvlm")
    assert "unknown backbone 'smolvlm' (did you mean 'smolvla'?)" in bad_backbone.stdout + bad_backbone.stderr
    bad_suite = bench_cli(tmp_path, "--suites", "spatail")
    assert "unknown suite 'spatail'" in bad_suite.stdout + bad_suite.stderr
    assert not (tmp_path / "results" / "cells").exists() or not any((tmp_path / "results" / "cells").iterdir())


def test_rollouts_on_synthetic_suites_fail_before_any_work(bench_cli, tmp_path):
    out = bench_cli(tmp_path, *SLICE, "--rollouts", "2")
    assert out.returncode != 0
    text = out.stdout + out.stderr
    assert "--rollouts: profile 'tiny' uses generated synthetic suites" in text
    assert "--profile sim" in text
    assert not (tmp_path / "results" / "cells").exists()


def test_a_record_from_another_normaliser_is_measured_again_not_resumed(bench_cli, tmp_path):
    one = ["--backbones", "pi05", "--suites", "spatial", "--encoders", "blind", "--seeds", "0",
           "--controls", "none", "--steps", "5"]
    first = bench_cli(tmp_path, *one)
    assert first.returncode == 0 and "measured 1, resumed from store 0" in first.stdout
    path = tmp_path / "results" / "cells" / "pi05-spatial-blind-seed0.json"
    record = json.loads(path.read_text())
    assert record["checkpoint"]["normalizer"] == "checkpoint"
    assert len(record["checkpoint"]["normalizer_fingerprint"]) == 12
    record["checkpoint"]["normalizer_fingerprint"] = "000000000000"  # measured under other stats
    path.write_text(json.dumps(record))
    again = bench_cli(tmp_path, *one)
    assert again.returncode == 0 and "measured 1, resumed from store 0" in again.stdout
    assert json.loads(path.read_text())["checkpoint"]["normalizer_fingerprint"] != "000000000000"
    third = bench_cli(tmp_path, *one)
    assert "measured 0, resumed from store 1" in third.stdout


def test_a_record_measured_on_other_weights_is_measured_again_not_resumed(bench_cli, tmp_path):
    """The tiny release's revision is its weights' hash: the same release key trained under
    another thread count (other bits) or another cache must not lend its records to this one."""
    one = ["--backbones", "pi05", "--suites", "spatial", "--encoders", "blind", "--seeds", "0",
           "--controls", "none", "--steps", "5"]
    assert bench_cli(tmp_path, *one).returncode == 0
    path = tmp_path / "results" / "cells" / "pi05-spatial-blind-seed0.json"
    record = json.loads(path.read_text())
    assert record["checkpoint"]["repo_id"] == "tiny:pi05"
    assert record["checkpoint"]["revision"].startswith("sha256:")
    record["checkpoint"]["revision"] = "sha256:0000000000000000"  # another release's weights
    path.write_text(json.dumps(record))
    again = bench_cli(tmp_path, *one)
    assert again.returncode == 0 and "measured 1, resumed from store 0" in again.stdout
    assert json.loads(path.read_text())["checkpoint"]["revision"] != "sha256:0000000000000000"


def test_controls_none_collects_no_empty_control_case(bench_cli, tmp_path):
    """Before: every `--controls none` run showed "1 skipped" (test_control[NOTSET])."""
    out = bench_cli(tmp_path, "--backbones", "pi05", "--suites", "spatial", "--encoders",
                    "pixels", "--seeds", "0", "--controls", "none", "--collect-only", "-q")
    assert out.returncode == 0, out.stdout[-2000:]
    assert "NOTSET" not in out.stdout and "::test_control[" not in out.stdout
    assert "1 test collected" in out.stdout
    assert not (tmp_path / "results" / "grid.json").exists()  # ids listed, nothing expected


def test_the_screen_start_line_counts_the_screens_that_will_run(bench_cli, tmp_path):
    """Before: "2 encoder(s) screened" when 4 ran (the references are screened too)."""
    out = bench_cli(tmp_path, "--backbones", "pi05", "--suites", "spatial", "--encoders",
                    "pixels,blind,dinov2_s,siglip", "--seeds", "0", "--controls", "none",
                    "--screen", "--screen-keep", "1", "--collect-only", "-q")
    assert out.returncode == 0, out.stdout[-2000:]
    assert ("[graftbench] --screen: 4 encoder(s) screened on each of 1 backbone x suite (4 "
            "screens, the references pixels, blind included); grafted: the best 1 of the 2 "
            "listed by logme, and the references") in out.stdout, out.stdout[-2000:]
    assert out.stdout.count("::test_screen[") == 4
    assert not (tmp_path / "results" / "grid.json").exists()  # under --screen: at the end
