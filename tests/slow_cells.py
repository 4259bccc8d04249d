"""A pytest plugin (`-p tests.slow_cells`) for tests of two runs at once: each cell this run
measures leaves a mark (GRAFTBENCH_TEST_MARKS/<cell_id>.<pid>) and then takes
GRAFTBENCH_TEST_CELL_DELAY seconds more, so a second run surely meets it being measured."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest


@pytest.hookimpl(trylast=True)  # after bench.plugin built the session
def pytest_configure(config: pytest.Config) -> None:
    from bench.plugin import SESSION_KEY

    session = config.stash[SESSION_KEY]
    from bench.cell.service import measure_here

    measure = session.seams.cell_runner or measure_here
    marks = Path(os.environ["GRAFTBENCH_TEST_MARKS"])
    delay = float(os.environ.get("GRAFTBENCH_TEST_CELL_DELAY", "0"))

    def slowly(cell, workspace, context):
        marks.mkdir(parents=True, exist_ok=True)
        (marks / f"{cell.id}.{os.getpid()}").touch()
        time.sleep(delay)
        return measure(cell, workspace, context)

    session.use_seams(cell_runner=slowly)
