"""The robustness tier in a grid run: the `--robustness` option and grid-file key, the cells that
get a `test_robust[...]` case, and the run's robustness cases (bench.robust.rescore measures one).

Off by default: without `--robustness` (or `robustness = [...]` in the grid file) no case is
collected and nothing here imports torch; the default run's records and protocol hash are those
of a run without this module.
"""

from __future__ import annotations

import dataclasses

import pytest

from bench.grid.cells import CellSpec, control_cells, graft_cells
from bench.grid.kinds import GRAFT, NATIVE, NATIVE_WRAPPED

OPTION = "--robustness"
# The cells a robustness case rescores: every graft, and the released policy's own references.
ROBUST_KINDS = (GRAFT, NATIVE, NATIVE_WRAPPED)


def add_robustness_option(group) -> None:
    group.addoption(OPTION, metavar="KIND[:SEVERITIES],...",
                    help="rescore every graft, native and native_wrapped cell on perturbed "
                         "held-out images, no retraining (cases test_robust[CELL_ID]): all, or "
                         "kinds of bench/robust/perturbations.py (brightness, contrast, colour, "
                         "noise, blur, camera_shift, occlusion), each at severities 1-3 unless "
                         "given, e.g. brightness,blur:1,3")


def with_robustness(profile, given: str | None):
    """`profile` with its robustness list checked and in canonical form ("kind:severity", table
    order): `--robustness` replaces the grid file's `robustness`. UsageError, one line, for an
    unknown kind or a severity out of range (exit 4, before anything runs)."""
    if given is not None:
        values, where = _split_kinds(given), f"{OPTION} {given}"
    else:
        values = list(profile.robustness)
        where = (f"{profile.grid_file.path}: robustness" if profile.grid_file is not None
                 else "robustness")
    if not values:
        return dataclasses.replace(profile, robustness=())
    from bench.robust.perturbations import parse_robustness

    try:
        applied = parse_robustness(values, where)
    except ValueError as e:
        raise pytest.UsageError(str(e)) from None
    return dataclasses.replace(profile, robustness=tuple(a.label for a in applied))


def _split_kinds(given: str) -> list[str]:
    """"brightness,blur:1,3,noise" -> ["brightness", "blur:1,3", "noise"]: a bare number after
    a colon belongs to the kind before it."""
    out: list[str] = []
    for part in (p.strip() for p in given.split(",")):
        if part.isdigit() and out and ":" in out[-1]:
            out[-1] += f",{part}"
        elif part:
            out.append(part)
    return out


def robust_cells(profile) -> list[CellSpec]:
    """The cells of the grid that get a robustness case (none when the tier is off)."""
    if not profile.robustness:
        return []
    cells = graft_cells(profile) + control_cells(profile)
    return [c for c in cells if c.kind in ROBUST_KINDS]


def applied(profile):
    """The profile's perturbations as bench.robust.perturbations.Applied."""
    from bench.robust.perturbations import parse_robustness

    return parse_robustness(profile.robustness, "robustness")


class RobustRun:
    """The run's robustness cases: one per selected cell, after every cell case, each resumed
    from its stored record or measured (its outcome kept for the session's end)."""

    def __init__(self, profile, workspace, rerun: bool = False) -> None:
        self.profile, self.workspace, self.rerun = profile, workspace, rerun
        self.outcomes: dict = {}  # cell id -> bench.cell.outcome.Outcome

    def run(self, cell: CellSpec):
        """The robustness record of `cell`; the case fails in one line (naming the command that
        measures what is missing) when the cell has no stored record or projector."""
        from bench.cell.outcome import MEASURED, RESUMED, failed
        from bench.robust.rescore import RobustUnavailable, measure_robust
        from bench.robust.closed_loop import rolls_out

        ws = self.workspace()
        # with --rollouts N: native and the best graft also roll out under each perturbation
        episodes = ws.rollouts if ws.rollouts and rolls_out(cell, self.profile, ws.store) else 0
        try:
            record, measured = measure_robust(cell, ws, applied(self.profile), rerun=self.rerun,
                                              rollouts=episodes)
        except RobustUnavailable as e:
            unavailable = str(e)
        else:
            unavailable = None
        if unavailable is not None:  # failed outside `except`: no "During handling" second copy
            self.outcomes[cell.id] = failed(unavailable)
            pytest.fail(unavailable, pytrace=False)
        self.outcomes[cell.id] = MEASURED if measured else RESUMED
        return record
