"""A graft's shuffled_image and zero_image[eval] controls reuse the graft's trained projector
within a session, and score exactly what retraining it would have given."""

from __future__ import annotations

import pytest

from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY, with_overrides
from bench.cell.plan import shared_projector_key
from bench.cell.service import run_cell
from bench.results.store import ResultStore
from tests.worlds import lent_workspace

PROFILE = with_overrides(TINY, steps=12)


def workspace(tmp_path, name):
    return lent_workspace(PROFILE, ResultStore(tmp_path / name))


def test_which_cells_share_the_graft_projector():
    graft = CellSpec("graft", "pi05", "spatial", 0, "pixels")
    sharing = [CellSpec("shuffled_image", "pi05", "spatial", 0, "pixels"),
               CellSpec("zero_image", "pi05", "spatial", 0, "pixels", "eval")]
    own = [CellSpec("zero_image", "pi05", "spatial", 0, "pixels", "train"),
           CellSpec("pooling", "pi05", "spatial", 0, "pixels", "global"),
           CellSpec("lora", "pi05", "spatial", 0, "pixels"),
           CellSpec("native_wrapped", "pi05", "spatial", 0),
           CellSpec("shuffled_image", "pi05", "spatial", 0),
           CellSpec("graft", "pi05", "spatial", 1, "pixels")]
    key = shared_projector_key(graft, "cache")
    assert key is not None
    assert all(shared_projector_key(c, "cache") == key for c in sharing)
    assert all(shared_projector_key(c, "cache") != key for c in own)
    assert shared_projector_key(graft, "loop") is None


@pytest.mark.parametrize("backbone", ["smolvla", "pi05"])
def test_controls_reuse_the_graft_projector_and_score_as_if_retrained(tmp_path, backbone):
    graft = CellSpec("graft", backbone, "spatial", 0, "pixels")
    shuffled = CellSpec("shuffled_image", backbone, "spatial", 0, "pixels")
    zero_eval = CellSpec("zero_image", backbone, "spatial", 0, "pixels", "eval")

    shared, projectors = workspace(tmp_path, "shared"), {}  # what a session keeps
    g = run_cell(graft, shared, projectors=projectors)
    reused = [run_cell(c, shared, projectors=projectors) for c in (shuffled, zero_eval)]
    assert g.training.projector_from is None
    for record in reused:
        assert record.training.projector_from == graft.id
        assert record.training.loss_curve == g.training.loss_curve
        assert record.training.probe_loss == g.training.probe_loss
        assert record.scores.mse != g.scores.mse  # evaluated on other inputs than the graft

    # Alone in a fresh session each control trains its own projector: same numbers.
    for spec, record in zip((shuffled, zero_eval), reused):
        alone = run_cell(spec, workspace(tmp_path, f"alone-{spec.kind}"))
        assert alone.training.projector_from is None
        assert alone.scores.mse == record.scores.mse
        assert alone.scores.per_window == record.scores.per_window
