"""`pytest bench --screen` (bench.cell.screening, bench.plugin, the report's screen section) on the
tiny world: screens stored before the grafts and resumed by a rerun, only the best K grafted
beside the pixels/blind references, the dropped cells skipped saying why, REPORT.md's section;
an encoder whose extraction fails is a failed screen and the screen goes on."""

from __future__ import annotations

import dataclasses

import pytest

from bench.grid.cells import CellSpec
from bench.grid.kinds import GRAFT
from bench.grid.protocol import TINY
from bench.results.store import ResultStore, load_results
from bench.cell.screening import ScreenRun
from bench.cell.service import CellService, RunSettings
from bench.screen.records import ScreenFailure, ScreenRecord
from bench.screen.selection import ScreenOptions
from bench.cell.outcome import MEASURED, RESUMED

SCREENED = ("dinov2_s", "fastvit", "repvit")  # ranked by the screen; pixels, blind: references
# Steps kept small: no margin between encoders is read here, only which cells ran.
ARGS = ("--screen", "--encoders", ",".join(("pixels", "blind") + SCREENED), "--backbones",
        "smolvla", "--suites", "spatial", "--seeds", "0", "--controls", "none", "--steps", "12",
        "-v", "-rs")


@pytest.fixture(scope="module")
def keep_two(tmp_path_factory):
    """On one results dir: the screens alone (-k), then a --screen-keep 2 run naming a
    calibration study (fabricated: 5 encoders, a perfect screen; under 6 its agreement is "not
    measured", which spares this run the 2,000-resample bootstrap, ~3.4 s: the measured numbers
    are test_tiers' calibration test), then its rerun."""
    from tests.bench_inprocess import run_bench
    from tests.factories import make_calibration_study

    folder = tmp_path_factory.mktemp("screen")
    where = ("--results-dir", str(folder / "results"), "--report", str(folder / "REPORT.md"))
    screens = run_bench(*where, *ARGS, "-k", "test_screen")
    screens_report = (folder / "REPORT.md").read_text() if (folder / "REPORT.md").exists() else ""
    make_calibration_study(folder / "calib", {f"timm:model_{i}": 0.05 + 0.01 * i
                                              for i in range(5)})
    top_two = ("--screen-keep", "2", "--screen-calibration", str(folder / "calib"))
    first_graft = GridAtFirstGraft(folder / "results")
    first = run_bench(*where, *ARGS, *top_two, figures=True, plugins=(first_graft,))
    again = run_bench(*where, *ARGS, *top_two)
    return folder, first, again, (screens, screens_report), first_graft.expected


class GridAtFirstGraft:
    """What grid.json expects when the run's first graft starts: what a run stopped there
    leaves for the report to list missing cells from."""

    def __init__(self, results) -> None:
        self.results, self.expected = results, None

    def pytest_runtest_setup(self, item):
        if self.expected is None and item.name.startswith("test_graft["):
            self.expected = load_results(self.results).expected


def test_the_screens_alone_run_with_k_and_report(keep_two):
    _, first, _, (screens, report), *_ = keep_two
    assert screens.returncode == 0, screens.stdout[-3000:]
    assert "screens 5: measured 5, resumed from store 0, failed 0" in screens.stdout
    assert "test_graft[" not in screens.stdout and "## Screening many encoders" in report
    assert "screens 5: measured 0, resumed from store 5" in first.stdout  # the next run's


def test_the_best_two_by_logme_are_grafted_with_the_references(keep_two):
    folder, first, _, _, at_first_graft = keep_two
    assert first.returncode == 0, first.stdout[-3000:]
    results = load_results(folder / "results")
    gains = {s.scores.encoder: s.scores.score("logme") for s in results.screens}
    assert set(gains) == {"pixels", "blind", *SCREENED} and not results.screen_failures
    best = sorted(SCREENED, key=lambda e: -gains[e])  # the planted rule, computed here
    grafted = {r.encoder for r in results.records if r.kind == GRAFT}
    assert grafted == {"pixels", "blind", *best[:2]}, (gains, grafted)
    [chosen] = results.selections
    assert chosen.kept == tuple(best[:2]) and chosen.by == "logme"
    dropped = f"smolvla-spatial-{best[2]}-seed0"
    assert "SKIPPED" in first.stdout and "dropped by the screen: logme rank 3 of 3" in first.stdout
    assert f"dropped {dropped}: logme rank 3 of 3" in first.stdout
    screen_at = first.stdout.index("test_screen[smolvla-spatial-pixels]")
    assert screen_at < first.stdout.index("test_graft[smolvla-spatial-pixels-seed0]")
    assert dropped not in load_results(folder / "results").expected  # grid.json: what ran
    # ... written at start-up too, every selected cell (a stopped run's report lists the missing)
    assert dropped in at_first_graft
    assert set(at_first_graft) - set(load_results(folder / "results").expected) == {
        dropped}


def test_a_rerun_resumes_every_screen_and_graft(keep_two):
    _, _, again, _, *_ = keep_two
    assert again.returncode == 0, again.stdout[-3000:]
    assert "screens 5: measured 0, resumed from store 5, failed 0" in again.stdout
    # 4 grafts and 10 short grafts (every encoder, the dropped one too, at 1/8 and 1/4)
    assert "measured 0, resumed from store 14, failed 0" in again.stdout


def test_the_report_shows_the_screen_its_cost_and_what_it_dropped(keep_two):
    folder, _, _, _, *_ = keep_two
    text = (folder / "REPORT.md").read_text()
    section = text[text.index("## Screening many encoders"):]
    section = section[:section.index("\n## ", 1)]
    assert "| LogME gain" in section and "Cost per encoder" in section
    assert "not measured: 4 encoder(s) have both the logme score" in section  # < 6: no agreement
    assert "logme rank 3 of 3" in section and "references pixels, blind" in section
    assert "screen_scatter.png" in section


def test_the_top_k_report_quotes_the_calibration_study_it_names(keep_two):
    folder, _, _, _, *_ = keep_two
    [chosen] = load_results(folder / "results").selections
    assert chosen.calibration == str((folder / "calib").resolve())
    text = (folder / "REPORT.md").read_text()
    part = text[text.index("**The agreement of the calibration study this run names**"):]
    part = part[:part.index("\n## ", 1)]
    assert f"as measured by the calibration study `{chosen.calibration}` over its 5" in part
    assert "0 of this run's 5 encoder(s) are among them" in part  # said, not hidden
    logme = next(line for line in part.splitlines() if "| logme " in line)
    assert "not measured: 5 encoder(s) have both the logme score" in logme  # the study's own


def test_a_failed_extraction_is_a_failed_screen_and_the_screen_goes_on(tiny_ws, tmp_path):
    class OneEncoderBreaks:
        """The tiny workspace, except that dinov2_s's extraction fails."""

        def __getattr__(self, name):
            return getattr(tiny_ws, name)

        def features(self, encoder, *args, **kwargs):
            if encoder == "dinov2_s":
                raise RuntimeError("CUDA out of memory\n while extracting")
            return tiny_ws.features(encoder, *args, **kwargs)

    store, ws = ResultStore(tmp_path), OneEncoderBreaks()
    profile = dataclasses.replace(TINY, encoders=("pixels", "blind", "dinov2_s"))
    run = ScreenRun(ScreenOptions(1), CellService(profile, store, lambda: ws, RunSettings()))
    chosen = run.selection("smolvla", "spatial")
    failure = store.load_screen("smolvla-spatial-dinov2_s")
    assert isinstance(failure, ScreenFailure)
    assert failure.error == "RuntimeError: CUDA out of memory while extracting"
    assert isinstance(store.load_screen("smolvla-spatial-blind"), ScreenRecord)
    assert chosen.kept == () and chosen.references == ("pixels", "blind")
    cell = CellSpec(GRAFT, "smolvla", "spatial", 0, "dinov2_s")
    assert run.dropped_reason(cell) == "its screen failed: " + failure.error
    assert run.dropped_reason(CellSpec(GRAFT, "smolvla", "spatial", 0, "pixels")) is None
    later = ScreenRun(ScreenOptions(1), CellService(profile, store, lambda: tiny_ws, RunSettings()))
    assert isinstance(later.screen("smolvla", "spatial", "dinov2_s"), ScreenRecord)  # re-screened
    later.screen("smolvla", "spatial", "blind")
    assert later.outcomes == {"smolvla-spatial-dinov2_s": MEASURED,
                              "smolvla-spatial-blind": RESUMED}
    other_dtype = dataclasses.replace(later.conditions("smolvla", "spatial"), feature_dtype="bf16")
    assert store.current_screen("smolvla-spatial-blind", other_dtype) is None


def test_a_screen_another_worker_is_measuring_is_waited_for_and_resumed(tiny_ws, tmp_path):
    """-n N: a worker whose selection needs a screen that another worker is measuring waits on
    the screen's lock (ResultStore.screen_lock), then resumes what that worker stored."""
    import threading

    from bench.screen.proxies import ENTROPY, proxy_names
    from bench.screen.records import ScreenScores, new_screen_record

    store = ResultStore(tmp_path)
    profile = dataclasses.replace(TINY, encoders=("pixels", "blind"))
    cells = CellService(profile, store, lambda: tiny_ws, RunSettings())
    run = ScreenRun(ScreenOptions(None), cells)
    theirs = ScreenScores("blind", "smolvla", "spatial", seconds=9.0)
    # Every proxy of the table (entropy in its own field): a record that stands for the run.
    theirs.proxies = {p: {"gain": 0.0} for p in proxy_names() if p != ENTROPY}
    theirs = new_screen_record(theirs, run.conditions("smolvla", "spatial"), 1.0)
    got = []
    waiter = threading.Thread(target=lambda: got.append(run.screen("smolvla", "spatial", "blind")))
    with store.screen_lock(theirs.screen_id):  # the other worker, measuring
        waiter.start()
        waiter.join(timeout=0.5)
        assert waiter.is_alive(), run.outcomes  # it waits rather than measuring
        store.write_screen(theirs)
    waiter.join(timeout=60)
    assert run.outcomes == {theirs.screen_id: RESUMED}
    assert got[0].to_json() == theirs.to_json()


def test_the_registered_ladder_is_ranked_in_its_planted_order(tiny_ws, tmp_path):
    """pixels_res8..1, blind (encoders.known.LADDER): information falls by construction,
    and every supervised proxy recovers that order exactly; the entropy is only measured."""
    from bench.analysis.agreement import kendall_tau_b
    from bench.screen.proxies import supervised_proxies
    from encoders.known import LADDER

    profile = dataclasses.replace(TINY, encoders=LADDER)
    cells = CellService(profile, ResultStore(tmp_path), lambda: tiny_ws, RunSettings())
    run = ScreenRun(ScreenOptions(None), cells)
    screens = [run.screen("smolvla", "spatial", e).scores for e in LADDER]
    planted = list(range(len(LADDER), 0, -1))  # higher is better: pixels first
    for proxy in (p.name for p in supervised_proxies()):
        scores = [s.score(proxy) for s in screens]
        assert kendall_tau_b(scores, planted) == pytest.approx(1.0), (proxy, scores)


def test_more_kept_than_listed_is_allowed_and_said(bench_cli, tmp_path):
    out = bench_cli(tmp_path, "--screen", "--encoders", "dinov2_s,fastvit", "--screen-keep", "5",
                    "--collect-only", "-q")
    assert out.returncode == 0, out.stdout[-2000:]
    assert ("--screen-keep 5 is more than the 2 listed encoder(s) (references aside): all are "
            "grafted") in out.stdout
    assert "included, added to --encoders)" in out.stdout  # pixels, blind: always grafted
    ids = [line for line in out.stdout.splitlines() if "::test_" in line]
    assert ids[0].endswith("test_screen[smolvla-spatial-dinov2_s]") and len(
        [i for i in ids if "test_screen[" in i]) == 8  # 2 backbones x (2 listed + 2 references)


def test_screen_files_are_validated_round_trip_and_a_bad_one_is_skipped(tmp_path):
    from bench.screen.records import (ScreenConditions, ScreenScores, ScreenSelection,
                                      new_screen_record)
    from bench.stats import Undefined

    store = ResultStore(tmp_path)
    scores = ScreenScores("timm:resnet10t", "pi05", "object", entropy=Undefined("no tokens"))
    scores.proxies = {"ridge": {"state": 0.4, "state+features": 0.3, "gain": 0.1}}
    record = new_screen_record(scores, ScreenConditions("abc", "fp", "fp16"), 1.5)
    path = store.write_screen(record)
    assert path.name == "pi05-object-timm_resnet10t.json"
    again = store.load_screen("pi05-object-timm_resnet10t")
    assert again.to_json() == record.to_json() and again.scores.entropy == Undefined("no tokens")
    store.write_selection(ScreenSelection("pi05", "object", "ridge", 1, ("a",), ("pixels",)))
    path.write_text(path.read_text().replace('"gain"', '"gian"'))
    assert store.load_screen("pi05-object-timm_resnet10t") is None  # measured again
    results = load_results(tmp_path)
    assert results.screens == [] and results.selections[0].kept == ("a",)
    assert results.skipped == [("screens/pi05-object-timm_resnet10t.json",
                                "ValueError: proxy ridge has no gain")]
