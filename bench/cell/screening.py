"""The --screen part of one pytest run: every screen resumed or measured once, and each backbone x
suite's graft selection decided once, after all its screens exist.

A `test_screen[...]` case and a graft cell's selection both go through `ScreenRun.screen`: a
screen the selection needs that no case ran (deselected with -k, or run on another xdist worker)
is resumed from the store or measured by the same code. An encoder that fails to build or
extract leaves a ScreenFailure with its one-line reason; the other screens go on, and the
selection drops it with that reason.

Under `--screen-by short` the selection waits for the short grafts (kind short_graft, variant
SHORT_BY_VARIANT) of every listed encoder and seed instead: each is run or resumed through
`run_tier` (the cell service's `run`, which claims the cell: the same plan, store and records as
its `test_short_graft` case); one that fails drops its encoder with the failure's line.
"""

from __future__ import annotations


import pytest

from bench.grid.cells import CellSpec
from bench.grid.kinds import SHORT_BY_VARIANT, SHORT_GRAFT
from bench.progress import say
from bench.cell.outcome import MEASURED, OUTCOME_PROPERTY, Outcome, Status, failed
from bench.screen.records import (ScreenConditions, ScreenFailure, ScreenRecord, ScreenSelection,
                                  screen_id)
from bench.screen.selection import (DEFAULT_SCREEN_BY, REFERENCES, SHORT, ScreenOptions,
                                    ShortScores, select_for_graft)
from bench.stats import Undefined

DROPPED = "dropped by the screen: "  # the skip line of a cell the screen dropped


class ScreenRun:
    """Screens and selections of one run, measured through the run's cell service `cells`
    (bench.cell.service: its `screen` for a screen, its `run` for a short graft)."""

    def __init__(self, options: ScreenOptions, cells) -> None:
        self.options, self.cells = options, cells
        self.profile, self.store, self.workspace = cells.profile, cells.store, cells.workspace
        self.outcomes: dict[str, Outcome] = {}  # screen id -> what became of it
        self.dropped: dict[str, str] = {}  # cell id -> why the screen dropped it
        self._screens: dict[str, ScreenRecord | ScreenFailure] = {}
        self._selections: dict[tuple[str, str], ScreenSelection] = {}

    def conditions(self, backbone: str, suite: str) -> ScreenConditions:
        return self.cells.screen_conditions(backbone, suite)

    def screen(self, backbone: str, suite: str, encoder: str) -> ScreenRecord | ScreenFailure:
        """The encoder's screen on backbone x suite through the cell service; once per run."""
        sid = screen_id(backbone, suite, encoder)
        if sid not in self._screens:
            item, outcome = self.cells.screen(backbone, suite, encoder)
            self._screens[sid], self.outcomes[sid] = item, outcome
            if outcome.status is not Status.RESUMED:
                self._say(sid, item)
        return self._screens[sid]

    def _say(self, sid: str, item) -> None:
        if isinstance(item, ScreenFailure):
            text = f"screen {sid}: FAILED {item.error}"
        else:
            by = DEFAULT_SCREEN_BY if self.options.by == SHORT else self.options.by  # a proxy
            gain = item.scores.score(by)
            shown = f"{gain:.4g}" if isinstance(gain, float) else str(gain)
            text = (f"screen {sid}: {by} gain {shown} ({item.feature_seconds:.1f} s "
                    f"features, {item.scores.seconds:.1f} s screen)")
        say(self.workspace().progress, text)

    def selection(self, backbone: str, suite: str) -> ScreenSelection:
        """What is grafted on backbone x suite: decided from every listed encoder's screen
        (missing ones measured here), stored for the report, once per run."""
        key = (backbone, suite)
        if key not in self._selections:
            references = tuple(e for e in self.profile.encoders if e in REFERENCES)
            if self.options.by == SHORT:
                scores, failed = self.short_scores(backbone, suite), {}
            else:
                items = [self.screen(backbone, suite, e) for e in self.profile.encoders]
                scores = [i.scores for i in items if isinstance(i, ScreenRecord)]
                failed = {i.encoder: i.error for i in items if isinstance(i, ScreenFailure)}
            chosen = select_for_graft(backbone, suite, scores, self.options, references, failed)
            self.store.write_selection(chosen)
            self._selections[key] = chosen
            say(self.workspace().progress,
                f"screen {backbone} x {suite}: grafting {', '.join(chosen.kept) or 'none'} "
                f"({f'the best {chosen.keep}' if chosen.keep else 'all'} by {chosen.by}) and the "
                "references "
                f"{', '.join(chosen.references) or 'none'}; dropped {len(chosen.dropped)}")
        return self._selections[key]

    def short_scores(self, backbone: str, suite: str) -> list[ShortScores]:
        """Each listed non-reference encoder's short graft at SHORT_BY_VARIANT, normalised MSE
        mean over the seeds: every one run or resumed here first (through `run_tier`)."""
        out = []
        for encoder in (e for e in self.profile.encoders if e not in REFERENCES):
            mses, error = [], None
            for seed in self.profile.seeds:
                cell = CellSpec(SHORT_GRAFT, backbone, suite, seed, encoder, SHORT_BY_VARIANT)
                try:
                    mses.append(self.run_tier(cell).mse_in())
                except (Exception, pytest.fail.Exception) as e:  # noqa: BLE001 - the rest go on
                    error = " ".join(str(e).split()) or type(e).__name__
                    break
            out.append(ShortScores(encoder, Undefined(f"its short graft failed: {error}")
                                   if error else sum(mses) / len(mses)))
        return out

    def run_tier(self, cell: CellSpec):
        """A tier cell (a short graft) run or resumed through the cell service, which claims
        the cell: its case and, under --screen-by short, the selection both run it, perhaps on
        two xdist workers at once; the later one waits, then resumes the record the first
        stored."""
        return self.cells.run(cell)

    def note_report(self, case_id: str, report) -> None:
        """What a pytest report says of a screen case (its outcome, a property) or of a cell the
        screen dropped (its skip line): how an xdist controller learns what its workers did."""

        if case_id in self._screens or case_id in self.dropped:
            return  # done here: this process knows already
        if report.skipped:
            line = report.longrepr[-1] if isinstance(report.longrepr, tuple) else ""
            if DROPPED in line:
                self.dropped[case_id] = line.split(DROPPED, 1)[1]
        elif report.passed:
            told = dict(report.user_properties).get(OUTCOME_PROPERTY)
            self.outcomes[case_id] = Outcome.of_text(told) if told else MEASURED
        elif report.failed:
            self.outcomes[case_id] = failed(report.longreprtext.strip().splitlines()[-1])

    def dropped_reason(self, cell) -> str | None:
        """Why the screen drops `cell` (a cell of a listed, non-reference encoder that was not
        kept), else None. Cells without an encoder (native, native_wrapped) always run."""
        if (cell.encoder is None or cell.encoder not in self.profile.encoders
                or cell.spec.tier):  # a tier runs for every screened encoder
            return None
        chosen = self.selection(cell.backbone, cell.suite)
        if chosen.grafts(cell.encoder):
            return None
        reason = chosen.dropped.get(cell.encoder, "not kept")
        self.dropped[cell.id] = reason
        return reason
