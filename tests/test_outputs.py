"""No file the user did not name as output is overwritten (bench.outputs, the one rule): the
report of `pytest bench` and of `python -m bench.report`, a saved baseline, an export folder.
Each case was seen writing over the file before its fix; now each stops with exit 4 in one line
naming the option, the value and the fix, every file under the folder byte for byte as it was.
In this process: a fraction of a second a case.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import backbones  # noqa: F401  (imported before pytester's sys.modules snapshot)
import encoders  # noqa: F401
from tests.bench_inprocess import bench_run  # noqa: F401  (the fixture)
from tests.factories import make_record, save_record
from tests.test_bad_inputs import assert_one_screen, report

pytest_plugins = ["pytester"]
CELL = make_record().cell_id  # smolvla-spatial-dinov2_s-seed0


def files(folder: Path) -> dict[str, bytes]:
    """Every file below `folder`, by relative path, with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def user_files(folder: Path) -> None:
    """A results dir with one record, a saved baseline, a user's notes.md and data.json."""
    save_record(folder / "results", make_record())
    (folder / "baselines").mkdir()
    (folder / "baselines" / "keep.json").write_text('{"schema": 1, "cells": {}}')
    (folder / "notes.md").write_text("my notes\n")
    (folder / "data.json").write_text('{"mine": 1}\n')


# --- pytest bench ---------------------------------------------------------------------------
# (arguments, what the screen says): before, each ran and wrote over the file, exit 0.
BENCH_CASES = [
    (["--rerun", "--report", f"{{tmp}}/results/cells/{CELL}.json"],
     f"--report {{tmp}}/results/cells/{CELL}.json: inside the record tree of the results dir"),
    (["--report", "{tmp}/notes.md"], "--report {tmp}/notes.md: the file exists and is not a "
     "graftbench report"),
    (["--report", "{tmp}/data.json"], "is not a graftbench report (its first line is not"),
    (["--save-baseline", "docs/EXPORT.md"], "--save-baseline docs/EXPORT.md: a baseline is a NAME"),
    (["--save-baseline", "a/b"], "no folder separator, '..' or .json), stored as NAME.json in "
     "--baseline-dir; fix: --save-baseline b"),
    (["--save-baseline", "../escape"], "fix: --save-baseline escape"),
    (["--save-baseline", "ok.json"], "fix: --save-baseline ok "),
    (["--save-baseline", "keep"], "--save-baseline keep: {tmp}/baselines/keep.json exists; fix: "
     "add --replace-baseline to replace it"),
    (["--replace-baseline"], "--replace-baseline: it lets --save-baseline replace"),
]


@pytest.mark.parametrize("args, says", BENCH_CASES, ids=[" ".join(a) for a, _ in BENCH_CASES])
def test_pytest_bench_never_writes_over_what_it_does_not_own(bench_run, args, says):
    tmp = bench_run.path
    user_files(tmp)
    before = files(tmp)
    args = [a.format(tmp=tmp) for a in args] + ["--baseline-dir", str(tmp / "baselines")]
    assert_one_screen(bench_run(*args), says.format(tmp=tmp))
    assert files(tmp) == before


def test_a_report_with_fewer_cells_needs_the_flag(bench_run):
    """Before: `-k` of one cell replaced a 40-cell report with a 1-cell one, without a word.
    (A named report: the default one is the run's own output, which a slice replaces.)"""
    tmp = bench_run.path
    (tmp / "REPORT.md").write_text("# graftbench report\n\nforty cells\n")
    (tmp / "REPORT_summary.json").write_text(json.dumps(
        {"answer": [], "cells": {"finished": 39, "failed": ["x"]}}))
    before = files(tmp)
    out = bench_run("-k", "pi05-spatial-pixels-seed0", "--report", str(tmp / "REPORT.md"))
    assert out.ret == 4 and (f"--report {tmp / 'REPORT.md'}: the report there holds 40 cell(s) "
                             "and this one would hold at most 1; fix: add --replace-report") \
        in out.screen, out.screen
    assert "Traceback" not in out.screen and files(tmp) == before
    assert not (tmp / "results").exists()  # the folders opening the store made: removed


# --- python -m bench.report -------------------------------------------------------------------
@pytest.mark.parametrize("target, says", [
    (f"results/cells/{CELL}.json", "inside the record tree of the results dir"),
    ("baselines/keep.json", "is not a graftbench report"),
    ("notes.md", "is not a graftbench report"),
    ("data.json", "is not a graftbench report"),
    ("notes", "the report's summary JSON would replace {tmp}/notes_summary.json, which graftbench "
     "did not write"),
], ids=["a-record", "a-baseline", "notes.md", "data.json", "a-companion"])
def test_bench_report_never_writes_over_what_it_does_not_own(tmp_path, capsys, target, says):
    user_files(tmp_path)
    (tmp_path / "notes_summary.json").write_text("{}")
    before = files(tmp_path)
    code, out, err = report([tmp_path / "results", "--no-plots", "--report", tmp_path / target],
                            capsys)
    assert code == 4 and out == "" and err.count("\n") == 1, err
    assert f"--report {tmp_path / target}: " in err and says.format(tmp=tmp_path) in err, err
    assert files(tmp_path) == before


def test_bench_report_into_a_folder_it_cannot_make_stops_before_the_report(tmp_path, capsys):
    """Before: the report was built, then its folder failed with a traceback (exit 1). /proc
    takes no new folder, not even root's (CI's user)."""
    user_files(tmp_path)
    before = files(tmp_path)
    target = Path("/proc/graftbench-no-such-folder/REPORT.md")
    code, out, err = report([tmp_path / "results", "--no-plots", "--report", target], capsys)
    assert code == 4 and out == "" and err.count("\n") == 1, err
    assert f"--report {target}: {target.parent}: not writable" in err, err
    assert files(tmp_path) == before


def test_an_unreadable_record_stops_the_report_unless_asked(tmp_path, capsys):
    """Before: 1 record of 2 corrupt, exit 0, the complete report replaced by a 1-cell one."""
    results = tmp_path / "results"
    save_record(results, make_record())
    save_record(results, make_record(encoder="pixels"))
    code, _, _ = report([results, "--no-plots", "--resamples", "20"], capsys)
    assert code == 0
    (results / "cells" / "smolvla-spatial-pixels-seed0.json").write_text("{not json")
    before = files(tmp_path)
    code, out, err = report([results, "--no-plots", "--resamples", "20"], capsys)
    assert code == 4 and err.count("\n") == 1 and files(tmp_path) == before, err
    assert "1 record file(s) cannot be read: cells/smolvla-spatial-pixels-seed0.json" in err
    assert "existing report kept; fix: repair or remove them, or add --skip-unreadable" in err
    # Asked to report what was readable: one cell of two, fewer than the report holds.
    code, _, err = report([results, "--no-plots", "--resamples", "20", "--skip-unreadable"],
                          capsys)
    assert code == 4 and "holds 2 cell(s) and this one would hold at most 1; fix: add " \
        "--replace-report" in err, err
    code, out, err = report([results, "--no-plots", "--resamples", "20", "--skip-unreadable",
                             "--replace-report"], capsys)
    assert code == 0 and "(1 finished" in out and "skipped 1 unreadable file(s)" in err, err


def test_an_export_into_the_record_tree_is_refused(tmp_path, capsys):
    from bench.export.__main__ import main

    save_record(tmp_path, make_record(encoder="timm:resnet18"))
    out = tmp_path / "cells" / "export"
    assert main([make_record(encoder="timm:resnet18").cell_id, "--results-dir", str(tmp_path),
                 "--out", str(out)]) == 4
    err = capsys.readouterr().err
    assert f"--out {out}: inside the record tree of the results dir {tmp_path}" in err, err
    assert not out.exists()


@pytest.mark.parametrize("name, replace, says", [
    ("ci", False, None), ("ci-2.nightly", False, None),
    ("a/b", False, "fix: --save-baseline b "), ("../escape", False, "fix: --save-baseline escape"),
    ("ok.json", False, "fix: --save-baseline ok "), ("keep", False, "add --replace-baseline"),
    ("keep", True, None),
])
def test_a_baseline_is_a_name_in_its_folder_and_is_replaced_only_when_asked(tmp_path, name,
                                                                            replace, says):
    from bench.outputs import baseline_refusal

    (tmp_path / "keep.json").write_text("{}")
    problem = baseline_refusal("--save-baseline", name, tmp_path, replace)
    assert problem is None if says is None else says in problem, problem
