"""docs/EXTENDING.md's "A report section": one entry in bench.report.build.SECTIONS (a title and a
function of the ReportContext) puts it in REPORT.md, in the table's order; a function that
returns None leaves its heading out, one that raises is shown as its error, not a lost report."""

from __future__ import annotations

import pytest

from bench.report import build
from tests.factories import make_record
from tests.test_report import write_grid


def _encoders_seen(ctx) -> str:
    """A toy section: the encoders of the stored grafts, read from the context."""
    names = sorted({r.encoder for r in ctx.records if r.encoder})
    return "Encoders stored: " + ", ".join(names)


@pytest.fixture
def results(tmp_path):
    records = [make_record(encoder=e, seed=s, level=0.05 + 0.01 * i)
               for i, e in enumerate(("siglip", "dinov2_s")) for s in (0, 1)]
    return write_grid(tmp_path / "results", records)


def _report(results, tmp_path) -> str:
    out = build.build_report(results, tmp_path / "REPORT.md", n_resamples=50, plots=False)
    return out.read_text()


def test_one_entry_puts_a_section_in_the_report_in_table_order(results, tmp_path, monkeypatch):
    table = list(build.SECTIONS)
    at = [t for t, _ in table].index("Tie bands")
    table.insert(at, ("Encoders seen", _encoders_seen))
    monkeypatch.setattr(build, "SECTIONS", table)
    text = _report(results, tmp_path)
    assert "## Encoders seen\n\nEncoders stored: dinov2_s, siglip" in text
    assert text.index("## Rank transfer") < text.index("## Encoders seen") < text.index("## Tie")


def test_a_section_returning_none_is_left_out_and_one_that_raises_is_named(
        results, tmp_path, monkeypatch):
    def broken(ctx):
        raise ValueError("no such column")

    table = list(build.SECTIONS) + [("Nothing here", lambda ctx: None), ("Broken", broken)]
    monkeypatch.setattr(build, "SECTIONS", table)
    text = _report(results, tmp_path)
    assert "## Nothing here" not in text
    broken_part = text.split("## Broken", 1)[1]
    assert "ValueError" in broken_part and "no such column" in broken_part
