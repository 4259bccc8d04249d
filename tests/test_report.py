"""REPORT.md built from stored records: every section renders, links resolve, tables are sound."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest

from tests.factories import make_failed, make_grid, make_record, save_record
from bench.results.store import load_results
from bench.report.build import SECTIONS, build_report
from bench.report.cli import main
from bench.report.screen import SECTION_TITLE
from bench.report.tuning import TITLE as TUNING_TITLE
from bench.report.family_scale import TITLE as FAMILY_SCALE_TITLE
from bench.report.working_group import TITLE as WORKING_TITLE

ENCODERS = ("siglip", "dinov2_s", "fastvit", "repvit")
RESAMPLES = 200
# Sections left out when their records are absent: screens (test_screen_run), robustness,
# tuned encoders (tests/test_tuned_encoder.py).
HEADINGS = [title for title, _ in SECTIONS
            if title not in (SECTION_TITLE, "Robustness", TUNING_TITLE, WORKING_TITLE,
                             FAMILY_SCALE_TITLE)]


def full_grid() -> list[dict]:
    levels = {}
    for i, enc in enumerate(ENCODERS):
        levels["smolvla", "spatial", enc] = 0.070 + 0.003 * i
        levels["smolvla", "object", enc] = 0.050 + 0.002 * i
        levels["pi05", "object", enc] = 0.020 + 0.001 * i
    levels |= {("pi05", "spatial", e): v for e, v in
               zip(ENCODERS, (0.0267, 0.0256, 0.0290, 0.0300))}
    records = make_grid(levels, (0, 1), noise=0.001,
                        native={("smolvla", "spatial"): (0.10, 0.15),
                                ("pi05", "spatial"): (0.02, 0.01)})
    records += [make_record(kind="lora", encoder="dinov2_s", level=0.068),
                make_record(kind="pooling", encoder="dinov2_s", variant="global", level=0.09),
                make_record(kind="zero_image", encoder="dinov2_s", variant="eval", level=0.2),
                make_record(kind="shuffled_image", encoder=None, level=0.3)]
    return records


def write_grid(root: Path, records: list[dict], expected: list[dict] | None = None) -> Path:
    for r in records:
        save_record(root, r)
    ids = [r.cell_id for r in (expected if expected is not None else records)]
    (root / "grid.json").write_text(json.dumps({"expected": ids, "profile": "tiny"}))
    return root


def check_markdown(path: Path) -> str:
    """Assert GitHub-markdown sanity: links resolve, tables are rectangular, fences close."""
    text = path.read_text(encoding="utf-8")
    for target in re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", text):
        assert not target.startswith(("/", "http")), f"image link not relative: {target}"
        assert (path.parent / target).is_file(), f"image link to a missing file: {target}"
    assert text.count("```") % 2 == 0, "unbalanced code fence"
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if not lines[i].startswith("|"):
            i += 1
            continue
        assert i > 0 and lines[i - 1].strip() == "", f"table without blank line before: {i}"
        block = []
        while i < len(lines) and lines[i].startswith("|"):
            block.append(lines[i])
            i += 1
        assert len(block) >= 2 and re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", block[1]), block[:2]
        widths = {len(re.split(r"(?<!\\)\|", line)) - 2 for line in block}
        assert len(widths) == 1, f"table with rows of different column counts: {block[0]}"
    return text


@pytest.fixture(scope="module")
def full_report(tmp_path_factory) -> tuple[Path, str]:
    root = write_grid(tmp_path_factory.mktemp("full"), full_grid())
    save_record(root, make_failed(encoder="broken", error="Traceback\nRuntimeError: out | of"))
    (root / "cells" / "garbage.json").write_text("{not json")
    out = build_report(root, root / "REPORT.md", n_resamples=RESAMPLES,
                       extra_sections=[("Against baseline", "| a | b |\n|---|---|\n| 1 | 2 |")])
    return out, check_markdown(out)


def test_full_report_sections_and_answer(full_report):
    out, text = full_report
    for title in HEADINGS + ["Against baseline"]:
        assert f"\n## {title}\n" in text
    assert "could not be rendered" not in text
    assert ("Transfer on suite **spatial**: the small-backbone winner (**siglip** on smolvla) "
            "**is not** in the large backbone's (pi05) top tier") in text
    assert "tiny" in text and "say **nothing** about real VLAs" in text
    assert "p >= 0.0833" in text
    assert "+50.0%" in text and "-50.0%" in text  # wrapper neutrality 0.10 -> 0.15, 0.02 -> 0.01
    assert "not closed-loop" in text.replace("**", "")
    assert text.index("## Provenance") < text.index("## Against baseline")


def test_full_report_lists_failed_and_skipped(full_report):
    out, text = full_report
    assert "smolvla-spatial-broken-seed0" in text and "RuntimeError: out \\| of" in text
    assert "cells/garbage.json" in text
    assert len(re.findall(r"!\[", text)) == 3


def test_csv_and_json_beside_the_report(full_report):
    out, _ = full_report
    with open(out.parent / "REPORT_cells.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(full_grid()) + 1
    assert {r["status"] for r in rows} == {"ok", "failed"}
    summary = json.loads((out.parent / "REPORT_summary.json").read_text())
    assert summary["support"]["comparisons_total"] == 4
    assert summary["wrapper_neutrality"]["smolvla x spatial"]["mean"]["normalized"] == \
        pytest.approx(0.5)
    assert summary["cells"]["failed"] == ["smolvla-spatial-broken-seed0"]


def test_half_grid_renders_every_section_and_lists_missing(tmp_path):
    records = full_grid()
    kept = records[::2]
    kept = [r for r in kept if r.backbone == "smolvla" or r.suite != "object"]
    write_grid(tmp_path, kept, expected=records)
    out = build_report(tmp_path, tmp_path / "out" / "REPORT.md", n_resamples=RESAMPLES)
    text = check_markdown(out)
    for title in HEADINGS:
        assert f"\n## {title}\n" in text
    assert "could not be rendered" not in text
    assert "needs both backbones" in text and "pi05 has no graft cells on object" in text
    missing = [r.cell_id for r in records if r not in kept]
    assert f"{len(missing)} missing of {len(records)} expected" in text
    for cell_id in missing:
        assert f"`{cell_id}`" in text


def test_one_backbone_and_empty_results_do_not_crash(tmp_path):
    smol = [r for r in full_grid() if r.backbone == "smolvla"]
    out = build_report(write_grid(tmp_path / "one", smol), n_resamples=RESAMPLES, plots=False)
    assert out == tmp_path / "one" / "REPORT.md"
    text = check_markdown(out)
    assert "needs both backbones" in text and "could not be rendered" not in text
    (tmp_path / "empty").mkdir()
    text = check_markdown(build_report(tmp_path / "empty", n_resamples=RESAMPLES, plots=False))
    assert "No finished cells" in text and "could not be rendered" not in text


def test_window_mismatch_is_reported_not_raised(tmp_path):
    records = [make_record(encoder="siglip"),
               make_record(encoder="dinov2_s", window_ids=list(range(100, 124)))]
    text = check_markdown(build_report(write_grid(tmp_path, records), n_resamples=RESAMPLES,
                                       plots=False))
    assert "Not ranked" in text and "other held-out windows" in text


def test_load_results_skips_bad_files(tmp_path):
    write_grid(tmp_path, [make_record()])
    diverged = make_record(encoder="x", per_window=[0.1, 0.2]).to_json()  # a valid one, then NaN
    diverged["per_window"]["normalized"][1] = float("nan")
    (tmp_path / "cells" / "nan.json").write_text(json.dumps(diverged))
    res = load_results(tmp_path)
    assert [r.cell_id for r in res.records] == ["smolvla-spatial-dinov2_s-seed0"]
    assert res.skipped and "non-finite" in res.skipped[0][1] and res.missing == []


def test_cli_entry_point(tmp_path, capsys):
    write_grid(tmp_path, full_grid()[:8])
    assert main([str(tmp_path), "--out", str(tmp_path / "R.md"), "--resamples", "50",
                 "--no-plots"]) == 0
    assert (tmp_path / "R.md").is_file() and "wrote" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([str(tmp_path / "nope")])


def vision_grid() -> list[dict]:
    """smolvla x spatial: siglip clearly beats blind; pi05 x spatial: blind ties the best graft;
    smolvla x object: no blind or zero_image control."""
    levels = {("smolvla", "spatial", "siglip"): 0.05, ("smolvla", "spatial", "dinov2_s"): 0.06,
              ("smolvla", "spatial", "blind"): 0.08, ("pi05", "spatial", "siglip"): 0.030,
              ("pi05", "spatial", "dinov2_s"): 0.031, ("pi05", "spatial", "blind"): 0.030,
              ("smolvla", "object", "siglip"): 0.05, ("smolvla", "object", "dinov2_s"): 0.06}
    return make_grid(levels, (0, 1), noise=0.002)


def test_report_flags_rankings_that_measure_nothing(tmp_path):
    out = build_report(write_grid(tmp_path, vision_grid()), n_resamples=RESAMPLES, plots=False)
    text = check_markdown(out)
    answer = text[:text.index("## Caveats")]
    assert "**Encoder rankings that measure nothing**" in answer
    assert "pi05 x spatial (siglip not better than blind graft)" in answer
    assert "**But the ranking on pi05 x spatial measures nothing**" in answer
    assert "Vision use not checked on smolvla x object" in answer
    caveat_text = text[text.index("## Caveats"):text.index("## Encoder rankings")]
    assert "Flagged (best graft not better than its blind / zero-image control): " \
        "pi05 x spatial." in caveat_text
    # next to each ranking: flagged, passed, unchecked
    rankings = text[text.index("## Encoder rankings"):text.index("## Vision use")]
    blocks = dict(re.findall(r"### (\S+ x \S+)\n\n(.*?)(?=\n### |\Z)", rankings, re.S))
    assert "**this encoder ranking says nothing**" in blocks["pi05 x spatial"]
    assert "beats every no-vision control" in blocks["smolvla x spatial"]
    assert "Vision use not checked: run the blind or zero_image control." in \
        blocks["smolvla x object"]
    assert "says nothing" not in blocks["smolvla x spatial"] + blocks["smolvla x object"]
    summary = json.loads((out.parent / "REPORT_summary.json").read_text())
    assert {(v["backbone"], v["suite"]): v["status"] for v in summary["vision_use"]} == {
        ("smolvla", "spatial"): "uses vision", ("pi05", "spatial"): "FLAGGED",
        ("smolvla", "object"): "unchecked"}


def test_provenance_lists_study_constants_and_disagreements(full_report):
    out, text = full_report
    provenance = text[text.index("## Provenance"):]
    assert "**Protocol constants: the study's and ours.**" in provenance
    assert re.search(r"\| learning rate +\| 0\.0001 +\| 0\.003 +\| \*\*DISAGREES\*\*", provenance)
    # Rows equal to the study's or ours where it is silent: in the JSON, not the table.
    assert "| warmup_steps " not in provenance and "key `protocol_constants`" in provenance
    (rows,) = json.loads((out.parent / "REPORT_summary.json").read_text())[
        "protocol_constants"].values()
    assert {"constant": "warmup_steps", "study": "not given", "ours": "30",
            "status": "ours (study silent)", "field": "warmup_steps",
            "note": "Protocol field"} in rows
    assert "Disagreements with the study under" in provenance
    assert "learning rate (study 0.0001, ours 0.003)" in provenance
    assert "**Constants that differ from the published study's**" in text
