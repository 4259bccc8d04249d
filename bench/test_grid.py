"""The grid. One parametrised case per cell; ids read as the cell, so
`pytest bench -k "pi05 and spatial"` selects exactly that slice.

A case asserts what must hold of any cell (finite loss that went down, the freeze, a finite
recorded MSE); it never asserts a ranking: rankings are the report's business.
"""

import math

from bench.summary import OUTCOME_PROPERTY


def _check_record(record: dict, cell) -> None:
    assert record["cell_id"] == cell.id
    for space in ("normalized", "raw"):
        assert math.isfinite(record["mse"][space]), f"{cell.id}: {space} MSE not finite"
    assert record["n_windows"] == len(record["per_window"]["normalized"]) > 0
    if cell.trains_projector:
        # Freeze by construction, verified: trainable = projector (+ LoRA adapters).
        assert record["trainable_params"] == record["projector_params"] + record["lora_params"]
        assert all(math.isfinite(v) for _, v in record["loss_curve"])
        # The training curve is noisy (fresh flow noise each step); the probe loss is measured
        # on fixed frames, noise and time before and after training.
        probe = record["probe_loss"]
        assert probe["after"] < probe["before"], (
            f"{cell.id}: training did not reduce the probe loss ({probe['before']:.4f} -> "
            f"{probe['after']:.4f})"
        )
    else:
        assert record["trainable_params"] == 0


def test_graft(graft_cell, graft_session, record_property):
    _check_record(graft_session.run(graft_cell), graft_cell)
    record_property(OUTCOME_PROPERTY, graft_session.outcomes.get(graft_cell.id))


def test_control(control_cell, graft_session, record_property):
    _check_record(graft_session.run(control_cell), control_cell)
    record_property(OUTCOME_PROPERTY, graft_session.outcomes.get(control_cell.id))
