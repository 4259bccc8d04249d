"""The short-graft tier (bench.grid.kinds short_graft): ids, steps and resume of the kind, and
`pytest bench --screen --screen-by short` on the tiny world: the selection runs the short grafts
it waits for, the short-graft cases run or resume them, their records say the steps they
trained, and REPORT.md's screen section has the tier's agreement row and cost."""

from __future__ import annotations

import pytest

from bench.grid.cells import CellSpec, tier_cells
from bench.grid.kinds import SHORT_BY_VARIANT, SHORT_GRAFT, control_kinds, get_kind
from bench.grid.protocol import TINY, with_overrides
from bench.results.current import RunConditions
from bench.results.store import ResultStore, load_results
from bench.cell.plan import plan, shared_projector_key
from tests.factories import make_record

STEPS = 12  # 1/8 -> 2 steps, 1/4 -> 3 (rounded up)
SCREENED = ("dinov2_s", "repvit")
ARGS = ("--screen", "--screen-by", "short", "--screen-keep", "1", "--encoders",
        ",".join(("pixels", "blind") + SCREENED), "--backbones", "smolvla", "--suites", "spatial",
        "--seeds", "0", "--controls", "none", "--steps", str(STEPS), "-v", "-rs")


def test_short_graft_ids_steps_and_what_it_is_not():
    cell = CellSpec(SHORT_GRAFT, "smolvla", "spatial", 0, "pixels", "1_8")
    assert cell.id == "smolvla-spatial-pixels-short_1_8-seed0"
    kind = get_kind(SHORT_GRAFT)
    assert [kind.scaled_steps(600, v) for v in kind.variants] == [75, 150]  # tiny-full
    assert [kind.scaled_steps(STEPS, v) for v in kind.variants] == [2, 3]
    assert kind.scaled_steps(0, "1_8") == 0 and kind.scaled_steps(1, "1_8") == 1
    assert SHORT_BY_VARIANT in kind.variants and SHORT_GRAFT not in control_kinds()
    # It trains its own (shorter) projector: never its graft's taken over.
    assert shared_projector_key(cell, "cache") is None
    profile = with_overrides(TINY, backbones=("smolvla", "pi05"), suites=("spatial",),
                             encoders=("pixels", "blind"), seeds=(0, 1))
    assert len(tier_cells(profile)) == 2 * 1 * 2 * 2 * 2  # backbones x suites x enc x seeds x 2


def test_a_stored_short_graft_resumes_and_another_fraction_does_not(tmp_path):
    store = ResultStore(tmp_path)
    stored = make_record(kind=SHORT_GRAFT, encoder="pixels", variant="1_4", train_steps=3)
    store.write(stored)
    run = RunConditions(protocol_hash=TINY.protocol.hash)
    quarter = CellSpec(SHORT_GRAFT, "smolvla", "spatial", 0, "pixels", "1_4")
    resumed = plan(quarter, store.load(quarter.id), run).resume
    assert resumed is not None and resumed.training.train_steps == 3
    eighth = CellSpec(SHORT_GRAFT, "smolvla", "spatial", 0, "pixels", "1_8")
    assert plan(eighth, store.load(eighth.id), run).resume is None
    assert load_results(tmp_path).records[0].reference == "smolvla-spatial-pixels-seed0"


@pytest.fixture(scope="module")
def by_short(tmp_path_factory):
    """One results dir: the grafts alone (-k test_graft: the selection must run the short grafts
    it ranks by), then the whole --screen run (screens, every short graft, grafts resumed)."""
    from tests.bench_inprocess import run_bench

    folder = tmp_path_factory.mktemp("short")
    where = ("--results-dir", str(folder / "results"), "--report", str(folder / "REPORT.md"))
    grafts_only = run_bench(*where, *ARGS, "-k", "test_graft")
    whole = run_bench(*where, *ARGS, figures=True)
    return folder, grafts_only, whole


def test_the_selection_runs_the_short_grafts_it_ranks_by(by_short):
    folder, grafts_only, _ = by_short
    assert grafts_only.returncode == 0, grafts_only.stdout[-3000:]
    assert "test_short_graft[" not in grafts_only.stdout  # deselected: the selection ran them
    results = load_results(folder / "results")
    [chosen] = results.selections
    assert chosen.by == "short" and chosen.keep == 1
    mse = {r.encoder: r.mse_in() for r in results.records
           if r.kind == SHORT_GRAFT and r.variant == SHORT_BY_VARIANT}
    best = min(SCREENED, key=lambda e: mse[e])  # the rule, computed here: lower MSE first
    assert chosen.kept == (best,), (mse, chosen)
    other = next(e for e in SCREENED if e != best)
    assert f"short rank 2 of 2 (MSE {mse[other]:.4g}), below the top 1" in chosen.dropped[other]
    assert "SKIPPED" in grafts_only.stdout and "dropped by the screen: short rank 2" in \
        grafts_only.stdout


def test_every_short_graft_is_stored_with_the_steps_it_trained(by_short):
    folder, _, whole = by_short
    assert whole.returncode == 0, whole.stdout[-3000:]
    records = load_results(folder / "results").records
    shorts = {(r.encoder, r.variant): r for r in records if r.kind == SHORT_GRAFT}
    assert set(shorts) == {(e, v) for e in ("pixels", "blind") + SCREENED
                           for v in ("1_8", "1_4")}  # every encoder, the dropped one too
    for (encoder, variant), r in shorts.items():
        steps = get_kind(SHORT_GRAFT).scaled_steps(STEPS, variant)
        assert r.training.train_steps == steps, (r.cell_id, r.training.train_steps)
        assert r.training.loss_curve[-1][0] == steps - 1  # what fit ran, not what was asked
        assert r.measured.protocol["steps"] == STEPS  # the run's protocol, resumable by hash
    grafts = [r for r in records if r.kind == get_kind(SHORT_GRAFT).reference("x")]
    assert grafts and all(r.training.train_steps == STEPS for r in grafts)
    # The selection's two 1/4 short grafts were resumed by their own cases, the rest measured.
    assert "test_short_graft[smolvla-spatial-pixels-short_1_8-seed0] PASSED" in whole.stdout
    assert "measured 6, resumed from store 5, failed 0" in whole.stdout  # 6 short, 3+2


def test_the_report_shows_the_short_tier_and_its_cost(by_short):
    folder, _, _ = by_short
    text = (folder / "REPORT.md").read_text()
    section = text[text.index("## Screening many encoders"):]
    section = section[:section.index("\n## ", 1)]
    row = next(line for line in section.splitlines() if "| short_1_4 " in line)
    assert "not measured: 3 encoder(s) have both the short_1_4 score" in row  # < 6 grafted
    assert "short_1_8 s / cell" in section and "short_1_4 s / cell" in section
    cost = next(line for line in section.splitlines() if line.startswith("| smolvla")
                and "no graft record" not in line and line.count("|") > 9)
    assert "no record" not in cost, cost
    assert (folder / "REPORT_plots" / "screen_scatter.png").exists()


def test_the_scatter_has_a_panel_per_short_tier(by_short):
    from bench.report.screen import scatter_points

    results = load_results(by_short[0] / "results")
    titles = [t for t, *_ in scatter_points([r.scores for r in results.screens], results.records)]
    assert "smolvla x spatial: short_1_4 (-MSE)" in titles
    assert "smolvla x spatial: short_1_8 (-MSE)" in titles


def test_screen_by_short_is_accepted_at_start_up_and_collects_the_tier(bench_cli, tmp_path):
    out = bench_cli(tmp_path, "--screen", "--screen-by", "short", "--encoders", "dinov2_s",
                    "--backbones", "smolvla", "--suites", "spatial", "--seeds", "0",
                    "--collect-only", "-q")
    assert out.returncode == 0, out.stdout[-2000:]
    assert "grafted: the best 3 of the 1 listed by short" in out.stdout
    ids = [line.split("::", 1)[1] for line in out.stdout.splitlines() if "::test_" in line]
    shorts = [i for i in ids if i.startswith("test_short_graft[")]
    assert len(shorts) == 3 * 2  # dinov2_s, pixels, blind x 1/8, 1/4
    assert "test_short_graft[smolvla-spatial-dinov2_s-short_1_4-seed0]" in shorts
    first_graft = next(n for n, i in enumerate(ids) if i.startswith("test_graft["))
    assert max(ids.index(i) for i in shorts) < first_graft  # the tier runs before the grafts


def test_a_short_graft_another_worker_is_running_is_waited_for(tmp_path):
    """-n N --screen-by short: the selection on one worker and the case on another both run a
    short graft through ScreenRun.run_tier, the cell service's run, which claims the cell
    (ResultStore.cell_lock): the later one waits, then its run resumes what the first stored."""
    import threading
    import types

    from bench.progress import QUIET
    from bench.screen.selection import ScreenOptions
    from bench.cell.screening import ScreenRun

    from bench.cell.plan import CellResult
    from bench.cell.service import CellService, RunSettings
    from tests.factories import make_record

    store = ResultStore(tmp_path)
    ran = []

    def runner(cell, ws, context):
        ran.append(cell.id)
        return CellResult(make_record(kind=cell.kind, encoder=cell.encoder, variant=cell.variant))

    quiet = types.SimpleNamespace(progress=QUIET)
    service = CellService(TINY, store, lambda: quiet, RunSettings(rerun=True), runner=runner)
    run = ScreenRun(ScreenOptions(1, "short"), service)
    cell = CellSpec(SHORT_GRAFT, "smolvla", "spatial", 0, "pixels", SHORT_BY_VARIANT)
    waiter = threading.Thread(target=run.run_tier, args=(cell,))
    with store.cell_lock(cell.id):  # the other worker, training it
        waiter.start()
        waiter.join(timeout=0.5)
        assert waiter.is_alive() and ran == []  # it waits rather than running it
    waiter.join(timeout=10)
    assert ran == [cell.id]
