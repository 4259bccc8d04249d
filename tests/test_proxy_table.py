"""bench.screen.proxies: the screen's proxy table. A proxy registered by one entry is measured by
the screen, kept in its record, offered by --screen-by and shown in the report's screen table;
the table imports without torch; no module spells a proxy's name but the table."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys

import pytest

from bench.grid.protocol import TINY
from bench.report.format import num
from bench.results.store import ResultStore
from bench.cell.outcome import MEASURED
from bench.cell.screening import ScreenRun
from bench.cell.service import CellService, RunSettings
from bench.screen.proxies import (HIGHER, LOWER, PROXIES, TOKEN_NORMS, WINDOWS, FitInputs, Proxy,
                                  get_proxy, proxy_names, register_proxy, unregister_proxy)
from bench.screen.records import ScreenScores, new_screen_record
from bench.screen.selection import ScreenOptions, parse_screen_by, screen_by_choices
from ondisk.paths import REPO_ROOT

BACKBONE, SUITE = "smolvla", "spatial"


def test_the_table_and_its_readers_import_without_torch():
    """The options, the records and the selection read the table at start-up: no torch there."""
    code = ("import sys, bench.screen.proxies, bench.screen.records, bench.screen.selection; "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO_ROOT, check=True)
    assert out.stdout.strip() == "False", out.stderr


def test_screen_by_offers_the_table_and_names_it_when_refused():
    assert screen_by_choices() == proxy_names() + ("short",)
    assert proxy_names() == ("logme", "ridge", "knn", "entropy", "param_count", "flops",
                             "resolution")  # the table's order: the naive baselines last
    with pytest.raises(ValueError, match=r"^--screen-by toy: unknown proxy; choose one of "
                                         r"logme, ridge, knn, entropy, param_count, flops, "
                                         r"resolution, short$"):
        parse_screen_by("toy")
    with pytest.raises(ValueError, match="unknown screen proxy 'toy'; valid proxies: logme,"):
        get_proxy("toy")


@pytest.mark.parametrize("field, value", [("direction", "up"), ("inputs", "pixels")])
def test_an_entry_with_a_bad_field_is_refused_naming_it(field, value):
    fields = dict(name="bad", label="bad", direction=HIGHER, inputs=WINDOWS, compute=len)
    with pytest.raises(ValueError, match=f"proxy 'bad': {field} '{value}' not in"):
        Proxy(**{**fields, field: value})


def test_no_module_spells_a_proxy_name_outside_the_table():
    """A proxy's name is a string in bench/screen/proxies.py only: everything else reads the
    table, so a new proxy is one entry."""
    literal = re.compile(rf"""["']({"|".join(map(re.escape, PROXIES))})["']""")
    offenders = [f"{path.relative_to(REPO_ROOT)}:{n}: {line.strip()}"
                 for path in sorted((REPO_ROOT / "bench").rglob("*.py"))
                 if path != REPO_ROOT / "bench/screen/proxies.py"
                 for n, line in enumerate(path.read_text().splitlines(), 1)
                 if literal.search(line.split("#")[0])]
    assert not offenders, "proxy names spelled outside the table:\n" + "\n".join(offenders)


def _columns(fit: FitInputs) -> tuple[float, int]:
    """The toy's value: how many input columns it is given; it 'chooses' the held-out count."""
    return float(fit.train.shape[1]), fit.heldout.n


def _largest_norm(norms) -> float:
    return float(norms.max())


TOYS = {
    # Known answer: its gain is the feature columns' count, dims[state+features] - dims[state].
    "supervised": Proxy("toy", "toy", HIGHER, WINDOWS, _columns, chooses="toy_heldout",
                        value_column="toy columns"),
    # Lower is better: its score is minus the largest token norm of the held-out windows.
    "label-free": Proxy("toy", "toy norm", LOWER, TOKEN_NORMS, _largest_norm),
}


@pytest.fixture(params=list(TOYS))
def toy_proxy(request):
    """One entry, taken out again after the test."""
    proxy = register_proxy(TOYS[request.param])
    yield proxy
    unregister_proxy(proxy.name)


def _screen_section(report: str) -> str:
    section = report[report.index("## Screening many encoders"):]
    end = section.find("\n## ", 1)
    return section if end < 0 else section[:end]


def test_a_toy_proxy_in_one_entry_is_screened_stored_selected_and_reported(
        toy_proxy, tiny_ws, tmp_path):
    from bench.report.build import build_report

    store = ResultStore(tmp_path / "results")
    profile = dataclasses.replace(TINY, encoders=("pixels", "blind", "dinov2_s"))
    cells = CellService(profile, store, lambda: tiny_ws, RunSettings())
    run = ScreenRun(ScreenOptions(1, toy_proxy.name), cells)
    # A screen stored before the toy existed does not stand: it is measured again.
    before = ScreenScores("blind", BACKBONE, SUITE, seconds=1.0)
    before.proxies = {p: {"gain": 0.0} for p in proxy_names() if p != toy_proxy.name}
    store.write_screen(new_screen_record(before, run.conditions(BACKBONE, SUITE), 1.0))
    chosen = run.selection(BACKBONE, SUITE)
    assert run.outcomes[f"{BACKBONE}-{SUITE}-blind"] == MEASURED

    screens = {e: store.load_screen(f"{BACKBONE}-{SUITE}-{e}").scores for e in profile.encoders}
    dino = screens["dinov2_s"]
    assert all(s.holds("toy") for s in screens.values()), screens
    if toy_proxy.supervised:
        expected = float(dino.dims["state+features"] - dino.dims["state"])
        assert dino.chosen["state"].get("toy_heldout") == dino.n_heldout, dino.chosen
        shown = [num(expected), num(dino.value("toy", "state+features"))]
    else:
        largest = dino.value("toy", "heldout")
        assert largest > 0, largest
        expected, shown = -largest, [num(largest, 3)]
    assert dino.score("toy") == expected
    assert chosen.by == "toy" and chosen.kept == ("dinov2_s",)  # the one non-reference

    report = build_report(store.root, tmp_path / "REPORT.md", n_resamples=20, plots=False)
    section = _screen_section(report.read_text())
    lines = section.splitlines()
    header = next(line for line in lines if line.startswith("| backbone ") and "encoder" in line)
    heads = [h.strip() for h in header.strip("|").split("|")]
    wanted = ["toy gain", "toy columns"] if toy_proxy.supervised else ["toy norm"]
    assert all(w in heads for w in wanted), heads
    row = next(line for line in lines if "| dinov2_s " in line)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert [cells[heads.index(w)] for w in wanted] == shown
    assert any(line.startswith(f"| {BACKBONE} ") and "| toy " in line for line in lines)
    assert "by toy: grafted dinov2_s" in section
