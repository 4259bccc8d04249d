"""One way to measure a cell: `CellService` takes a cell from its id to its record file.

For every cell kind (graft, control, short graft) and every executor: the pytest session (serial or
an xdist worker), a submitit / Slurm array task (bench.cell.executors.run_cell_job) and a script
outside pytest (`run_cell`) all call `CellService.run`. It claims the cell on the results store
(another process measuring it makes this one wait, then resume), sets an unreadable record aside,
reads the stored record once and plans (bench.cell.plan: resume it or measure, with what), measures
through its runner (bench.cell.runner, which returns and writes nothing) or its job array (the
first cell measured plans the array's cells and hands over those to measure; bench.cell.executors
submits them and returns each one's result), then alone writes what came of it: the record with
its projector file, or the failure record when measuring raised; it keeps the projector a later
cell takes, and returns the record with a typed outcome (bench.cell.outcome). The screen's
measurements go through `screen` alike (bench.cell.screening keeps only the selection), and its
short grafts through `run`. With `pack_grafts` > 1 a measured cell may lead a pack of graft cells
trained together (bench.cell.pack_run), each still claimed, written, failed and reported one by
one.

It imports nothing of pytest: the session turns what it raises into a case's failure.
Nothing it calls is handed the service: the plan, the pack, the job array and the runner return
to it.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from functools import partial
from typing import Callable, Sequence

from bench.grid.cells import CellSpec
from bench.progress import say
from bench.cell.outcome import MEASURED, RESUMED, Outcome, failed
from bench.cell.extend import rebuilds_policy
from bench.cell.plan import CellPlan, CellResult, plan


@dataclass(frozen=True)
class RunSettings:
    """How this run measures (its options, not the protocol): measure again whatever is stored
    (`rerun`), the features mode, the stored features' dtype, closed-loop episodes per task,
    graft cells trained per backbone pass (`pack_grafts`, bench.cell.pack_run; 1: one at a time)."""

    rerun: bool = False
    features_mode: str = "cache"
    feature_dtype: str = "fp16"
    rollouts: int = 0
    pack_grafts: int = 1


def measure_here(cell: CellSpec, ws, context) -> CellResult:
    """The default runner: the cell measured in this process (bench.cell.runner.measure)."""
    from bench.cell.runner import measure

    return measure(cell, ws, context)


class CellService:
    """Plans, measures and writes one cell at a time for one results store. `workspace()` gives
    the (lazy) workspace; `runner(cell, ws, context) -> CellResult` measures in this process;
    `job_array`, when given, measures elsewhere (bench.cell.executors.JobArray: `submit(plans)`,
    `result(plan) -> CellResult`): `array_candidates()`, the selected cells it may measure in run
    order, are planned here and those that do not resume handed to it at the first measurement;
    `feature_transform(cell)`: a planted degradation for the cell (the baseline's), or None;
    `order()`: the run's selected cell ids, for "cell i/n" in the start line;
    `pack_candidates(cell)`: the selected cells that may share `cell`'s pack, in run order
    (with `settings.pack_grafts` > 1; this service claims the mates that
    bench.cell.pack_run.may_join admits)."""

    def __init__(self, profile, store, workspace: Callable, settings: RunSettings, *,
                 runner: Callable = measure_here, job_array=None,
                 array_candidates: Callable[[], Sequence[CellSpec]] = tuple,
                 feature_transform: Callable = lambda cell: None,
                 order: Callable[[], Sequence[str]] = tuple, claim: bool = True,
                 projectors: dict | None = None,
                 pack_candidates: Callable[[CellSpec], Sequence[CellSpec]] = lambda cell: ()
                 ) -> None:
        self.profile, self.store, self.workspace, self.settings = profile, store, workspace, settings
        self.runner, self.job_array, self.array_candidates = runner, job_array, array_candidates
        self._array_submitted = False  # the job array: submitted once, at the first measurement
        self.feature_transform, self.order, self.claim = feature_transform, order, claim
        self.pack_candidates = pack_candidates
        # Projectors measured cells handed back (CellContext.keep_as): later plans take them.
        self.projectors: dict = {} if projectors is None else projectors
        self.records: dict = {}  # cell id -> the Record this service measured or resumed
        self.outcomes: dict[str, Outcome] = {}  # cell id -> what became of it
        # A pack mate whose training failed: its case raises this when reached (not retrained).
        self.pack_failures: dict[str, Exception] = {}
        self.set_aside_lines: list[str] = []  # unreadable records moved aside (store.set_aside)

    # --- one cell ---------------------------------------------------------------------------
    def run(self, cell: CellSpec):
        """The cell's record: resumed when the stored one stands for this run, else measured
        and written (a failure record when measuring raises, then the error)."""
        # A short graft the selection ran before its own case, or a mate of an earlier pack.
        if cell.id in self.records:
            return self.records[cell.id]
        if cell.id in self.pack_failures:  # its pack's training failed it: record written
            raise self.pack_failures[cell.id]
        with self._claim(cell):  # another process on this results dir: wait, then resume
            self.set_aside(cell)
            cell_plan = self.plan(cell)
            if cell_plan.resume is not None:
                record, outcome = cell_plan.resume, RESUMED
            elif cell_plan.extend is not None and self.job_array is None:
                # (a job array measures elsewhere: its task measures the cell again, rerun)
                record, outcome = self._extend(cell_plan), MEASURED
            else:
                record, outcome = self._measure(cell_plan), MEASURED
        self.records[cell.id], self.outcomes[cell.id] = record, outcome
        return record

    def plan(self, cell: CellSpec) -> CellPlan:
        """Resume or measure `cell` (bench.cell.plan.plan: reads the store, writes nothing)."""
        from bench.results.current import RunConditions

        s = self.settings
        run = RunConditions(protocol_hash=self.profile.protocol.hash,
                            feature_dtype=s.feature_dtype, rollouts=s.rollouts)
        return plan(cell, self.store.load(cell.id), run, workspace=self.workspace,
                    rerun=s.rerun, features_mode=s.features_mode, projectors=self.projectors,
                    feature_transform=self.feature_transform(cell),
                    rebuilds=partial(rebuilds_policy, results_dir=self.store.root))

    def progress(self):
        return self.workspace().progress

    def set_aside(self, cell: CellSpec) -> None:
        """Move `cell`'s unreadable stored record aside, saying so (call it under its claim)."""
        if (line := self.store.set_aside(cell.id)) is not None:
            self.set_aside_lines.append(line)
            say(self.progress(), line)

    # --- one screen ---------------------------------------------------------------------------
    def screen_conditions(self, backbone: str, suite: str):
        """What a screen of `backbone` x `suite` is measured under (stored with it)."""
        from bench.screen.records import ScreenConditions

        norm = self.workspace().normalizer(backbone, suite)
        return ScreenConditions(self.profile.protocol.hash, norm.fingerprint,
                                self.settings.feature_dtype)

    def screen(self, backbone: str, suite: str, encoder: str):
        """(the screen of `encoder` on `backbone` x `suite`, what became of it): the stored one
        when it stands for this run (not under rerun; holding every proxy of the table: one
        registered since is measured), else measured (bench.screen.measure) and written. A
        screen that fails is a ScreenFailure, written too: the other screens go on."""
        from bench.screen.measure import measure_screen
        from bench.screen.proxies import proxy_names
        from bench.screen.records import ScreenRecord, screen_id

        sid, conditions = screen_id(backbone, suite, encoder), self.screen_conditions(backbone, suite)
        # Under -n N a worker's selection may need a screen another worker is measuring (its
        # case, or its own selection): the lock makes it wait and resume that one.
        with self.store.screen_lock(sid):
            stored = None if self.settings.rerun else self.store.current_screen(sid, conditions)
            if stored is not None and all(map(stored.scores.holds, proxy_names())):
                return stored, RESUMED
            item = measure_screen(self.workspace(), encoder, backbone, suite, conditions)
            self.store.write_screen(item)
        return item, (MEASURED if isinstance(item, ScreenRecord) else failed(item.error))

    def _claim(self, cell: CellSpec):
        if not self.claim:  # a job array measures in its own tasks: the array is the claimant
            return contextlib.nullcontext()
        return self.store.cell_lock(cell.id, on_wait=lambda: say(
            self.progress(), f"{cell.id}: another process is measuring it (its claim "
                             f"{self.store.claim_path(cell.id)}); waiting for its record"))

    def _measure(self, cell_plan: CellPlan):
        cell = cell_plan.cell
        if cell_plan.discard:  # a degraded record never outlives its run
            self.store.forget(cell.id)
        self._say_start(cell_plan)
        try:
            if self.job_array is not None:
                result = self._measure_in_array(cell_plan)
            elif self.settings.pack_grafts > 1 and self.claim:
                result = self._measure_pack(cell_plan)  # with mates, when it finds them
            else:
                result = self.runner(cell, self.workspace(), cell_plan.context)
            return self.write(cell_plan, result)
        except Exception as e:
            self.note_failure(cell, e)
            raise

    def _measure_in_array(self, cell_plan: CellPlan) -> CellResult:
        """`cell_plan`'s result from its task in the job array. The first cell measured submits
        the array: the plans of `array_candidates()` that do not resume (each task measures its
        cell again, rerun, and writes it); every cell then waits for its own task."""
        if not self._array_submitted:
            # Once, even when planning or submitting raises: each later cell then fails as not
            # submitted (the array's KeyError, in its own failure record), never resubmitted.
            self._array_submitted = True
            plans = [p for c in self.array_candidates() if (p := self.plan(c)).resume is None]
            self.job_array.submit(plans)
        return self.job_array.result(cell_plan)

    def _measure_pack(self, lead: CellPlan) -> CellResult:
        """`lead`'s result, its cell trained in a pack with the mates this service claims
        (bench.cell.pack_run trains and scores; each mate is written here as it is scored, the
        lead returned last like a runner's result), or alone when it cannot lead or finds none."""
        from bench.cell import pack_run

        ws = self.workspace()
        with contextlib.ExitStack() as claims:  # the mates' claims, held until all are written
            mates = self._claim_mates(lead, claims) if pack_run.can_lead(lead) else []
            if not mates:
                return self.runner(lead.cell, ws, lead.context)
            plans = [lead] + mates
            say(self.progress(), f"pack of {len(plans)} grafts through one {lead.cell.backbone} "
                                 f"pass ({lead.cell.suite}): {', '.join(p.cell.id for p in plans)}")
            for mate in mates:
                if mate.discard:  # a degraded record never outlives its run
                    self.store.forget(mate.cell.id)
            items = pack_run.train(ws, plans)
            if items is None:  # the lead alone, as unpacked; the mates each meet it when reached
                return self.runner(lead.cell, ws, lead.context)
            for mate, item in zip(mates, items[1:]):
                try:
                    record = self.write(mate, pack_run.scored(ws, mate, item))
                except Exception as e:  # this mate alone fails; the pack's others go on
                    self.note_failure(mate.cell, e)
                    self.pack_failures[mate.cell.id] = e
                    continue
                self.records[mate.cell.id], self.outcomes[mate.cell.id] = record, MEASURED
            return pack_run.scored(ws, lead, items[0])

    def _claim_mates(self, lead: CellPlan, claims: contextlib.ExitStack) -> list[CellPlan]:
        """Plans of up to K-1 mates for `lead` (bench.cell.pack_run.may_join), each claimed without
        waiting (the claims entered on `claims`): one another process holds is left to it, and so
        is one whose plan resumes, extends or takes its graft's projector (its own case does)."""
        from bench.cell.pack_run import may_join

        wanted, mates = self.settings.pack_grafts - 1, []
        for mate in self.pack_candidates(lead.cell):
            if len(mates) == wanted:
                break
            if (mate.id == lead.cell.id or mate.id in self.records or mate.id in self.pack_failures
                    or not may_join(mate, lead.cell, self.settings.features_mode)):
                continue
            one = contextlib.ExitStack()
            if not one.enter_context(self.store.try_cell_lock(mate.id)):
                one.close()  # another process measures it: its record is its claimant's
                continue
            self.set_aside(mate)
            mate_plan = self.plan(mate)
            if (mate_plan.resume is not None or mate_plan.extend is not None
                    or mate_plan.context.reuse is not None):
                one.close()  # its case resumes / extends it, takes its graft's projector
                continue
            claims.enter_context(one.pop_all())
            mates.append(mate_plan)
        return mates

    def _extend(self, cell_plan: CellPlan):
        """The stored record with the episodes the run wants more of (bench.cell.extend), in
        this process (nothing trains), written as a measured one."""
        from bench.cell.extend import extend_rollouts

        cell, order = cell_plan.cell, list(self.order())
        position = order.index(cell.id) + 1 if cell.id in order else "?"
        have = (cell_plan.extend.run.rollouts or {}).get("episodes") or []
        say(self.progress(), f"cell {position}/{len(order)} {cell.id}: {len(have)} stored "
                             f"episode(s) kept, the rest of {self.settings.rollouts} per task "
                             "rolled out by its stored policy (nothing trained or rescored)")
        try:
            return self.write(cell_plan, extend_rollouts(cell, self.workspace(), cell_plan.extend))
        except Exception as e:
            self.note_failure(cell, e)
            raise

    def note_failure(self, cell: CellSpec, error: Exception) -> None:
        """`cell`'s failure record written and its outcome set (the error is the caller's)."""
        from bench.results.record import Failure

        self.store.write_failure(Failure.of(cell, self.profile.protocol.hash, error))
        self.outcomes[cell.id] = failed(f"{type(error).__name__}: {error}")

    def write(self, cell_plan: CellPlan, result: CellResult):
        """What measuring `cell_plan` gave, written (its projector file, then the record naming
        it; not when a job array's task wrote it) and kept: the projector a later cell takes
        (`CellContext.keep_as`), one line. Returns the record as written."""
        from bench.cell.projectors import keep_for_session, save_projector

        record, cell = result.record, cell_plan.cell
        if not result.stored:
            if result.projector is not None:
                file, sha = save_projector(self.store.root, cell.id, result.projector)
                record = record.replace(projector_file=file, projector_sha256=sha)
            self.store.write(record)
        if cell_plan.context.keep_as is not None and result.projector is not None:
            self.projectors[cell_plan.context.keep_as] = keep_for_session(
                self.workspace().session_dir(), record, result.projector)
        say(self.progress(), f"{record.cell_id}: MSE {record.mse_in():.4f} normalised "
                             f"({record.run.total_s:.1f} s)")
        return record

    def _say_start(self, cell_plan: CellPlan) -> None:
        cell, order = cell_plan.cell, list(self.order())
        position = order.index(cell.id) + 1 if cell.id in order else "?"
        say(self.progress(), f"cell {position}/{len(order)} {cell.id}: "
                             f"{cell_plan.work(self.profile.protocol.steps)} "
                             "offline MSE on the held-out windows")


def run_cell(cell: CellSpec, ws, features_mode: str = "cache", *, feature_transform=None,
             projectors: dict | None = None):
    """Measure one cell and write its record, outside a session (scripts, tests): the service
    with `rerun` (what is stored is measured again). `projectors`: a dict the caller keeps across
    calls, so a control takes its graft's trained projector; `feature_transform`: CellContext's."""
    settings = RunSettings(rerun=True, features_mode=features_mode,
                           feature_dtype=ws.feature_dtype, rollouts=ws.rollouts)
    service = CellService(ws.profile, ws.store, lambda: ws, settings,
                          feature_transform=lambda cell: feature_transform,
                          projectors=projectors)
    return service.run(cell)
