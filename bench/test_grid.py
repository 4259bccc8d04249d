"""The grid. One parametrised case per cell; ids read as the cell, so
`pytest bench -k "pi05 and spatial"` selects exactly that slice.

Under --screen, `test_screen[backbone-suite-encoder]` cases come first (bench.cell.screening),
then the short grafts `test_short_graft[...-short_1_8-seed0]` (a tier of the ladder).
Under --robustness, `test_robust[cell id]` cases come last: each rescores a stored cell on
perturbed held-out windows (bench.robust.rescore).
A case asserts what must hold of any cell (finite loss that went down, the freeze, a finite
recorded MSE); it never asserts a ranking: rankings are the report's business.
"""

import pytest

from bench.results.record import Record, validate_record
from bench.cell.outcome import OUTCOME_PROPERTY


def _tell(record_property, outcome) -> None:
    """The case's outcome (bench.cell.outcome) as a report property: how an xdist worker tells
    the controller what became of it."""
    record_property(OUTCOME_PROPERTY, outcome.text if outcome is not None else None)


def _check_record(record: Record, cell) -> None:
    """What the runner cannot check while it runs: a record resumed from disk is checked like a
    new one (the runner validates what it writes: finite scores, counts, the freeze), and
    training must have lowered the probe loss (fixed frames, noise and time, before vs after;
    the training curve itself is noisy)."""
    validate_record(record)
    assert record.cell_id == cell.id
    if cell.trains_projector:
        probe = record.training.probe_before_after
        assert probe is not None, f"{cell.id}: a trained cell without its probe loss"
        before, after = probe
        assert after < before, (
            f"{cell.id}: training did not reduce the probe loss ({before:.4f} -> {after:.4f})")


def test_screen(screen_case, graft_session, record_property):
    """--screen only, before the grafts: the encoder's proxies stored (or resumed); an encoder
    that cannot be built or extracted fails here in one line, and the screen goes on."""
    from bench.screen.records import ScreenFailure

    item = graft_session.screening.screen(screen_case.backbone, screen_case.suite,
                                          screen_case.encoder)
    if isinstance(item, ScreenFailure):
        pytest.fail(f"{screen_case.id}: {item.error}", pytrace=False)
    assert item.screen_id == screen_case.id
    _tell(record_property, graft_session.screening.outcomes.get(screen_case.id))


def test_short_graft(tier_cell, graft_session, record_property):
    """--screen only, after the screens and before the grafts: the graft at a fraction of its
    steps (bench.grid.kinds short_graft), for every listed encoder whatever the selection."""
    _check_record(graft_session.run(tier_cell), tier_cell)
    _tell(record_property, graft_session.outcomes.get(tier_cell.id))


def test_graft(graft_cell, graft_session, record_property):
    _check_record(graft_session.run(graft_cell), graft_cell)
    _tell(record_property, graft_session.outcomes.get(graft_cell.id))


def test_control(control_cell, graft_session, record_property):
    _check_record(graft_session.run(control_cell), control_cell)
    _tell(record_property, graft_session.outcomes.get(control_cell.id))


def test_robust(robust_cell, graft_session, record_property):
    """--robustness only, after every cell: the cell's stored projector rescored on perturbed
    held-out windows (bench.robust.rescore); every perturbation asked for is in the record."""
    record = graft_session.robustness.run(robust_cell)
    wanted = set(graft_session.profile.robustness)
    assert wanted <= {f"{e.kind}:{e.severity}" for e in record.entries}
    _tell(record_property, graft_session.robustness.outcomes.get(robust_cell.id))
