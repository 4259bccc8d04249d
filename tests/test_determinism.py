"""The same cell with the same seed gives the same MSE whatever ran before it in the process."""

from __future__ import annotations

import pytest
import torch

from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY, with_overrides
from bench.cell.service import run_cell
from bench.results.store import ResultStore
from tests.worlds import lent_workspace

PROFILE = with_overrides(TINY, steps=12)


@pytest.mark.parametrize("backbone", ["smolvla", "pi05"])
def test_lora_cell_does_not_depend_on_the_global_random_state(tmp_path, backbone):
    spec = CellSpec("lora", backbone, "spatial", 0, "pixels")
    ws = lent_workspace(PROFILE, ResultStore(tmp_path / "results"))
    torch.manual_seed(1)
    first = run_cell(spec, ws)
    torch.manual_seed(2)  # what earlier cells or tests drew from the global generator
    torch.rand(1000)
    again = run_cell(spec, ws)
    assert first.training.lora_params == again.training.lora_params > 0
    assert first.scores.mse == again.scores.mse
    assert first.scores.per_window == again.scores.per_window
