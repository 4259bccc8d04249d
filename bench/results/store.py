"""The results store: the one reader and writer of record files. Every record read is validated
(bench.results.record); every write is atomic. A results dir:

    RESULTS_DIR/cells/<cell_id>.json    finished cells  (status "ok", schema 1)
    RESULTS_DIR/failed/<cell_id>.json   failed cells    (status "failed", with "error")
    RESULTS_DIR/grid.json               optional: {"expected": [cell_id, ...], "profile": "tiny"}
    RESULTS_DIR/screens/...             the screen tier (--screen): bench.screen.records
    RESULTS_DIR/rollouts/<cell_id>.json closed-loop episodes of a cell still rolling out (EpisodeLog)
    RESULTS_DIR/unreadable/<cell_id>.<time>.json  a record that could not be read, moved aside
                                        before its cell was measured again (set_aside)
    RESULTS_DIR/.claims/<cell_id>.lock  the claim on a cell while a process measures it
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from bench.grid.kinds import GRAFT
from bench.results.episode_log import EpisodeLog
from bench.results.jsonfile import atomic_write_json, read_json as _read_json
from ondisk.filelock import exclusive, try_exclusive
from bench.results.current import RunConditions, is_current
from bench.results.record import Failure, Record
from bench.screen.records import (ScreenConditions, ScreenFailure, ScreenRecord, ScreenSelection,
                                  read_screen)

CELLS, FAILED, GRID = "cells", "failed", "grid.json"  # the folder and file names, only here
SCREENS, SELECTIONS = "screens", "selections"  # screens/, screens/selections/
ROLLOUTS = "rollouts"
CLAIMS = ".claims"  # hidden: a folder of lock files, no results
UNREADABLE = "unreadable"
_GRID_EXPECTED, _GRID_PROFILE = "expected", "profile"


class ResultsDirError(RuntimeError):
    pass


def _read_grid(root: Path) -> tuple[list[str], str | None]:
    """grid.json's (expected cell ids, profile); OSError / ValueError / KeyError / TypeError."""
    grid = _read_json(root / GRID)
    return [str(c) for c in grid[_GRID_EXPECTED]], grid.get(_GRID_PROFILE)


def read_record(path: Path) -> Record:
    """One validated record file; ValueError (or OSError) naming the problem."""
    try:
        return Record.from_json(_read_json(path))
    except (TypeError, AttributeError) as e:  # a field of the wrong JSON type
        raise ValueError(f"{type(e).__name__}: {e}") from None


@dataclass
class Results:
    """Everything a results dir holds, validated. `skipped` lists (path, reason) of bad files."""

    root: Path
    records: list[Record] = field(default_factory=list)
    failed: list[Failure] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    expected: list[str] | None = None
    grid_profile: str | None = None
    screens: list[ScreenRecord] = field(default_factory=list)
    screen_failures: list[ScreenFailure] = field(default_factory=list)
    selections: list[ScreenSelection] = field(default_factory=list)
    set_aside: list[str] = field(default_factory=list)  # unreadable/ file names (set_aside)

    @property
    def missing(self) -> list[str]:
        """Cell ids in grid.json that have neither a record nor a failure file."""
        if self.expected is None:
            return []
        seen = {r.cell_id for r in self.records} | {f.cell_id for f in self.failed}
        return [cid for cid in self.expected if cid not in seen]


def load_results(results_dir: str | Path) -> Results:
    """Read cells/, failed/ and grid.json under `results_dir` (creating nothing); bad files go to
    `skipped`."""
    root = Path(results_dir)
    results = Results(root=root)
    seen: set[str] = set()
    for path in sorted((root / CELLS).glob("*.json")):
        where = str(path.relative_to(root))
        try:
            record = read_record(path)
        except (OSError, ValueError) as err:
            results.skipped.append((where, f"{type(err).__name__}: {err}"))
            continue
        if record.cell_id in seen:
            results.skipped.append((where, f"duplicate cell_id {record.cell_id!r}"))
            continue
        seen.add(record.cell_id)
        results.records.append(record)
    for path in sorted((root / FAILED).glob("*.json")):
        try:
            failure = Failure.from_json(_read_json(path))
        except (OSError, ValueError) as err:
            results.skipped.append((str(path.relative_to(root)), f"{type(err).__name__}: {err}"))
            continue
        if failure.cell_id not in seen:  # a later successful rerun supersedes a failure
            results.failed.append(failure)
    _load_screens(root, results)
    results.set_aside = sorted(p.name for p in (root / UNREADABLE).glob("*.json"))
    if (root / GRID).exists():
        try:
            results.expected, results.grid_profile = _read_grid(root)
        except (OSError, ValueError, KeyError, TypeError) as err:
            results.skipped.append((GRID, f"{type(err).__name__}: {err}"))
    return results


def _screen_file(root: Path, sid: str) -> Path:
    return root / SCREENS / f"{sid.replace('/', '_')}.json"  # hub names may hold a slash


def _load_screens(root: Path, results: Results) -> None:
    """screens/*.json and screens/selections/*.json into `results` (bad files: skipped)."""
    for path in sorted((root / SCREENS).glob("*.json")):
        try:
            item = read_screen(_read_json(path))
        except (OSError, ValueError) as err:
            results.skipped.append((str(path.relative_to(root)), f"{type(err).__name__}: {err}"))
            continue
        (results.screens if isinstance(item, ScreenRecord) else results.screen_failures).append(item)
    for path in sorted((root / SCREENS / SELECTIONS).glob("*.json")):
        try:
            results.selections.append(ScreenSelection.from_json(_read_json(path)))
        except (OSError, ValueError) as err:
            results.skipped.append((str(path.relative_to(root)), f"{type(err).__name__}: {err}"))


def load_calibration(results_dir: str | Path) -> Results:
    """The results of a calibration study (a `--screen --screen-keep all` run's results dir):
    ValueError, one line, when the folder is missing, holds no finished screen, or holds no
    graft record of an encoder it screened on the same backbone x suite (nothing to agree with)."""
    root = Path(results_dir)
    if not root.is_dir():
        raise ValueError("no such results dir")
    results = load_results(root)
    if not results.screens:
        raise ValueError(f"no screen record there ({SCREENS}/*.json: it was not a --screen run)")
    screened = {(s.scores.backbone, s.scores.suite, s.scores.encoder) for s in results.screens}
    if not any(r.kind == GRAFT and (r.backbone, r.suite, r.encoder) in screened
               for r in results.records):
        raise ValueError(f"{len(results.screens)} screen(s) but no graft of a screened encoder "
                         f"there ({CELLS}/*.json): no agreement to quote")
    return results


def load_failure(results_dir: str | Path, cell_id: str) -> Failure | None:
    """The failure file of `cell_id` under `results_dir`; None when absent or unreadable."""
    path = Path(results_dir) / FAILED / f"{cell_id}.json"
    try:
        return Failure.from_json(_read_json(path)) if path.is_file() else None
    except (OSError, ValueError):
        return None


_HELD = threading.local()  # the cell claims this thread holds (ResultStore.cell_lock)


class ResultStore:
    """A writable results dir (layout: module docstring). A failure file is never used to skip
    work; a successful write clears it."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        # What opening makes, deepest first: removed again, while empty, by remove_if_unused.
        wanted = [self.root / CELLS, self.root / FAILED, self.root, *self.root.absolute().parents]
        self.made = [p for p in wanted if not p.exists()]
        try:
            (self.root / CELLS).mkdir(parents=True, exist_ok=True)
            (self.root / FAILED).mkdir(parents=True, exist_ok=True)
            # A private probe file: xdist workers open the same store at the same moment, and a
            # shared name let one worker's unlink break another's (a false "not writable").
            fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=self.root)
            os.close(fd)
            os.unlink(probe)
        except OSError as e:
            raise ResultsDirError(
                f"results dir {self.root} is not writable ({e.strerror}); "
                "pass a writable folder with --results-dir PATH"
            ) from None

    def remove_if_unused(self) -> None:
        """Remove the folders opening the store made, those still empty: a run stopped at
        start-up leaves nothing behind."""
        for folder in self.made:
            with contextlib.suppress(OSError):
                folder.rmdir()

    def stored_ids(self) -> set[str]:
        """Ids of the cells with a record or a failure here, by file name (none is read)."""
        return {p.stem for folder in (CELLS, FAILED) for p in (self.root / folder).glob("*.json")}

    def cell_path(self, cell_id: str) -> Path:
        return self.root / CELLS / f"{cell_id}.json"

    def failure_path(self, cell_id: str) -> Path:
        return self.root / FAILED / f"{cell_id}.json"

    def load(self, cell_id: str) -> Record | None:
        """The stored record of `cell_id`, validated; None when absent, unreadable or invalid
        (then it is measured again)."""
        path = self.cell_path(cell_id)
        if not path.exists():
            return None
        try:
            return read_record(path)
        except (OSError, ValueError):
            return None

    def current(self, cell_id: str, run: RunConditions) -> Record | None:
        """The stored record if it may stand for `run` (bench.results.current), else None."""
        record = self.load(cell_id)
        return record if record is not None and is_current(record, run) else None

    def forget(self, cell_id: str) -> None:
        """Remove a stored record (it is measured again)."""
        self.cell_path(cell_id).unlink(missing_ok=True)

    def write(self, record: Record) -> Path:
        path = self.cell_path(record.cell_id)
        atomic_write_json(path, record.to_json())
        self.failure_path(record.cell_id).unlink(missing_ok=True)
        self.episode_log(record.cell_id, "").clear()  # the record now holds its episodes
        return path

    def episode_log(self, cell_id: str, key: str) -> EpisodeLog:
        """The resumable episode log of `cell_id`'s rollouts under `key` (EpisodeLog)."""
        return EpisodeLog(self.root / ROLLOUTS / f"{cell_id}.json", key)

    def write_failure(self, failure: Failure) -> Path:
        path = self.failure_path(failure.cell_id)
        atomic_write_json(path, failure.to_json())
        return path

    def load_screen(self, sid: str) -> ScreenRecord | ScreenFailure | None:
        """The stored screen `sid` (bench.screen.records.screen_id); None when absent or invalid."""
        path = _screen_file(self.root, sid)
        try:
            return read_screen(_read_json(path)) if path.is_file() else None
        except (OSError, ValueError):
            return None

    def current_screen(self, sid: str, conditions: ScreenConditions) -> ScreenRecord | None:
        """The stored finished screen `sid` when measured under `conditions`, else None."""
        item = self.load_screen(sid)
        return item if isinstance(item, ScreenRecord) and item.conditions == conditions else None

    def screen_lock(self, sid: str):
        """Held while screen `sid` is looked up and measured: another process on this results
        dir (an xdist worker whose graft selection needs the same screen) waits, then finds it
        stored instead of measuring it twice."""
        path = _screen_file(self.root, sid)
        return exclusive(path.with_name(f".{path.stem}.lock"))

    def claim_path(self, cell_id: str) -> Path:
        # Not in cells/: that folder holds records only (readers list it). The files stay:
        # removing a lock file another process waits on would let a third take a new one.
        return self.root / CLAIMS / f"{cell_id}.lock"

    @contextlib.contextmanager
    def cell_lock(self, cell_id: str, on_wait=None):
        """The claim on a cell, held while it is planned and measured: another process on this
        results dir (a second run, an xdist worker, a --screen-by short selection) waits, then
        resumes the record the claimant stored, instead of measuring the cell twice. A flock:
        the kernel frees it when the claimant dies (kill -9). `on_wait()` is called once when
        the cell is claimed elsewhere, before waiting. Re-entrant within a thread (a short
        graft's selection claims it, then runs it through the session, which claims it too)."""
        path = self.claim_path(cell_id)
        held = _HELD.__dict__.setdefault("paths", set())
        if path in held:
            yield
            return
        with exclusive(path, on_wait=on_wait):
            held.add(path)
            try:
                yield
            finally:
                held.discard(path)

    @contextlib.contextmanager
    def try_cell_lock(self, cell_id: str):
        """`cell_lock` without waiting (a packed graft's mates, bench.cell.pack_run): yields True
        holding the claim, False at once when another process holds it (the cell is left to it).
        Within this thread a claim already held counts as held."""
        path = self.claim_path(cell_id)
        held = _HELD.__dict__.setdefault("paths", set())
        if path in held:
            yield True
            return
        with try_exclusive(path) as claimed:
            if claimed:
                held.add(path)
            try:
                yield claimed
            finally:
                if claimed:
                    held.discard(path)

    def set_aside(self, cell_id: str) -> str | None:
        """Move a stored record that cannot be read (truncated, not JSON, invalid) to
        unreadable/, keeping its bytes for a look; returns the one line that says so, or None
        when the record is absent or reads. Call it under the cell's claim."""
        path = self.cell_path(cell_id)
        if not path.exists():
            return None
        try:
            read_record(path)
            return None
        except (OSError, ValueError) as e:
            reason = " ".join(f"{type(e).__name__}: {e}".split())
        stamp = time.strftime("%Y%m%dT%H%M%S")
        aside = self.root / UNREADABLE / f"{cell_id}.{stamp}.json"
        aside.parent.mkdir(parents=True, exist_ok=True)
        for n in range(1, 1000):  # a second one within the same second keeps the first
            if not aside.exists():
                break
            aside = aside.with_name(f"{cell_id}.{stamp}-{n}.json")
        os.replace(path, aside)
        return (f"{CELLS}/{path.name} is unreadable ({reason}): moved to "
                f"{UNREADABLE}/{aside.name}; {cell_id} is measured again")

    def write_screen(self, item: ScreenRecord | ScreenFailure) -> Path:
        """A finished screen, or a failed one (replaced by the next success)."""
        path = _screen_file(self.root, item.screen_id)
        atomic_write_json(path, item.to_json())
        return path

    def write_selection(self, selection: ScreenSelection) -> Path:
        name = f"{selection.backbone}-{selection.suite}.json".replace("/", "_")
        path = self.root / SCREENS / SELECTIONS / name
        atomic_write_json(path, selection.to_json())
        return path

    def write_grid(self, expected: list[str], profile: str, add: bool = False,
                   drop: set[str] = frozenset()) -> None:
        """grid.json: the cells this run means to measure (the report lists those missing);
        `add` (a -k / -m slice): after what the folder's grid of the same profile expected, not
        instead of it, so a study run in slices reads as one study; `drop`: cells an earlier
        write of this run listed that it no longer expects (the screen's drops)."""
        try:
            kept, earlier = _read_grid(self.root) if add else ([], None)
        except (OSError, ValueError, KeyError, TypeError):
            kept, earlier = [], None
        if earlier == profile:
            kept = [c for c in kept if c not in drop]
            expected = kept + [c for c in expected if c not in set(kept)]
        atomic_write_json(self.root / GRID, {_GRID_EXPECTED: expected, _GRID_PROFILE: profile})

