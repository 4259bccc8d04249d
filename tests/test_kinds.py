"""The cell-kind table is the one definition of a kind: ids, --controls, records and the report
read it, and a kind added in one place shows up in all of them."""

from __future__ import annotations

import dataclasses
import json
import re

import pytest

from bench.grid import kinds
from bench.grid.cells import CellSpec, control_cells, graft_cells, tier_cells
from bench.grid.kinds import (CELL_KINDS, CellKind, control_kinds, register_kind, tier_kinds,
                              unregister_kind)
from ondisk.paths import REPO_ROOT
from bench.grid.protocol import TINY_FULL, with_overrides
from bench.results.record import validate_record
from tests.factories import make_record, save_record
from bench.results.store import load_results


def test_every_consumer_knows_the_same_kinds():
    """Cells, --controls, records and the report's control analysis read one table."""
    from bench.analysis.controls import control_deltas
    from bench.options import build_profile

    table = set(CELL_KINDS)
    everything = dataclasses.replace(TINY_FULL, controls=control_kinds(),
                                     control_encoders=("pixels",))
    in_cells = {c.kind for c in graft_cells(everything) + control_cells(everything)
                + tier_cells(everything)}
    assert in_cells == table
    tiers = {k.name for k in tier_kinds()}  # --screen's ladder: never a --controls name

    class Config:  # what build_profile reads of pytest's config
        def getoption(self, name):
            return {"--profile": "tiny", "--controls": ",".join(control_kinds())}.get(name)

    assert set(build_profile(Config()).controls) | {kinds.GRAFT} | tiers == table

    records = [make_record(kind=c.kind, encoder=c.encoder, variant=c.variant)
               for c in graft_cells(everything)[:1] + control_cells(everything)
               + tier_cells(everything)]
    for r in records:
        validate_record(r)  # every kind is a valid record kind
    compared = {cd.kind for cd in control_deltas(records)}
    assert compared == {k.name for k in CELL_KINDS.values() if k.control and not k.tier}
    with pytest.raises(ValueError, match="unknown cell kind"):
        validate_record({**records[0].to_json(), "kind": "retrained"})


def test_no_module_spells_a_kind_name_outside_the_table():
    """A kind's name is a string in bench/grid/kinds.py only (profiles name the controls they run,
    as they name encoders: bench/grid/protocol.py is allowed that)."""
    allowed = {"bench/grid/kinds.py", "bench/grid/protocol.py", "bench/test_grid.py"}
    names = "|".join(re.escape(n) for n in CELL_KINDS)
    literal = re.compile(rf"""["']({names})["']""")
    offenders = []
    for path in sorted((REPO_ROOT / "bench").rglob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        if rel in allowed:
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if literal.search(line.split("#")[0]):
                offenders.append(f"{rel}:{n}: {line.strip()}")
    assert not offenders, "kind names spelled outside bench/grid/kinds.py:\n" + "\n".join(offenders)


@pytest.fixture
def twin_kind():
    """A trivial control kind: the graft trained again from its seed. It trains exactly its
    graft's projector, so the table alone says it takes the graft's (known answer: delta 0)."""
    kind = register_kind(CellKind("twin", "the graft again, from the same seed"))
    yield kind
    unregister_kind(kind.name)


def test_a_new_control_kind_runs_records_and_reports(twin_kind, tmp_path):
    """Round trip: the runner writes the records, load_results reads them, the report shows
    the new kind; nothing but the table entry was added."""
    from bench.report.build import build_report
    from bench.cell.service import run_cell
    from bench.results.store import ResultStore
    from tests.worlds import lent_workspace

    profile = with_overrides(TINY_FULL, steps=20, backbones=("pi05",), suites=("spatial",),
                             encoders=("pixels",), seeds=(0,), controls=("native", "twin"))
    cells = graft_cells(profile) + control_cells(profile)
    assert [c.id for c in cells] == ["pi05-spatial-pixels-seed0", "pi05-spatial-native-seed0",
                                     "pi05-spatial-pixels-twin-seed0"]
    ws = lent_workspace(profile, ResultStore(tmp_path / "results"))
    projectors = {}  # kept across cells, as a session keeps them
    graft, _, twin = (run_cell(c, ws, projectors=projectors) for c in cells)
    assert twin.kind == "twin" and twin.reference == graft.cell_id
    assert twin.training.projector_from == graft.cell_id
    assert twin.scores.per_window == graft.scores.per_window  # same projector, same windows, same noise

    results = load_results(tmp_path / "results")
    assert not results.skipped and {r.kind for r in results.records} == {"graft", "native", "twin"}
    report = build_report(tmp_path / "results", tmp_path / "REPORT.md").read_text()
    row = next(line for line in report.splitlines() if "twin of pixels" in line)
    assert "+0.0%" in row or "+0.00%" in row or " 0.0%" in row, row


def test_fabricated_records_follow_the_writers_format(tmp_path):
    """Test records (tests.factories.make_record) carry the ids CellSpec gives and read back."""
    record = make_record(kind="pooling", encoder="pixels", variant="half")
    assert record.cell_id == CellSpec("pooling", "smolvla", "spatial", 0, "pixels", "half").id
    save_record(tmp_path, record)
    assert [r.to_json() for r in load_results(tmp_path).records] == \
        [json.loads(json.dumps(record.to_json()))]  # tuples: lists


def test_kind_table_rejects_what_the_runner_cannot_do():
    with pytest.raises(ValueError, match="training rule"):
        CellKind("bad", "shuffled training", train_inputs=((None, kinds.SHUFFLED),))
    with pytest.raises(ValueError, match="registered twice"):
        register_kind(CELL_KINDS["graft"])
