"""`--pack-grafts K` (bench.cell.pack_run): a run's graft cells trained K at a time through one
frozen-backbone pass write the records the unpacked run writes, deterministically; a mate with a
current record is resumed, not retrained; the grid file's `pack_grafts` packs too and the command
line wins over it; a bad K, or K > 1 with a job-array executor, stops at start-up (exit 4).

Tolerance: tests/test_packed.py measured packed cells bit-identical to their twins on CPU with
one torch thread; whole records are too (the runs below: every MSE, loss curve and projector
sha256 equal), so equality is asserted, not a tolerance."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from bench.grid.cells import CellSpec
from bench.grid.kinds import GRAFT
from bench.grid.protocol import TINY
from bench.option_values import pack_grafts
from bench.cell.outcome import MEASURED
from bench.cell.service import CellService, RunSettings
from bench.loops.train import NonFiniteLoss
from bench.results.store import read_record

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# Four graft cells of one backbone x suite (2 encoders x 2 seeds) and two shuffled_image controls
# per seed, of pixels (takes its graft's trained projector: never its pack mate) and of the native
# policy (trains nothing).
GRID = ["--backbones", "smolvla", "--suites", "spatial", "--encoders", "pixels,dinov2_s",
        "--seeds", "0,1", "--controls", "shuffled_image", "--steps", "4"]
FEW_WINDOWS = "[protocol]\neval_stride = 30\n"  # scoring, the cells' main cost here, 10x cheaper
KEPT = "smolvla-spatial-dinov2_s-seed0"  # the record the resume case keeps


def records(folder) -> dict[str, tuple]:
    """{cell id: what a cell's bits are}: its scores, loss curve, probe losses, steps, projector
    hash and origin (not its timings or creation time)."""
    out = {}
    for path in sorted((folder / "results" / "cells").glob("*.json")):
        r = read_record(path)
        t = r.training
        out[r.cell_id] = (r.scores, t.loss_curve, t.probe_loss, t.train_steps, t.projector_sha256,
                          t.projector_from)
    return out


def study(folder, pack_line: str = ""):
    """A grid file with few held-out windows (and `pack_line`), for --grid."""
    path = folder / "study.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(pack_line + FEW_WINDOWS)
    return str(path)


def run(bench_cli, folder, *args: str):
    out = bench_cli(folder, *GRID, *args, env={"GRAFTBENCH_QUIET": None})
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    return out


def packs(out) -> list[str]:
    """The packs' sizes, from their start lines."""
    return re.findall(r"pack of (\d+) grafts through one smolvla pass", out.stdout)


def test_packed_runs_write_the_unpacked_records_bit_for_bit(bench_cli, tmp_path):
    """Unpacked; packed by the grid key (6: the 4 grafts, not the controls); again with the key
    at 2 and --pack-grafts 6, which wins: the same packing, the same bits, and every record the
    unpacked run's (the controls' projector_from their graft's, as unpacked)."""
    alone = run(bench_cli, tmp_path / "alone", "--grid", study(tmp_path / "alone"))
    assert packs(alone) == [] and "measured 8, resumed from store 0" in alone.stdout
    unpacked = records(tmp_path / "alone")
    assert len(unpacked) == 8 and sum(r[-1] is not None for r in unpacked.values()) == 2
    # Each encoder's record names the runtime its stored features came from (64 px tiny
    # encoders: torch); the policy's own tower has no stored features.
    got = {r.cell_id: (r.encoder, r.measured.feature_runtime) for r in map(
        read_record, (tmp_path / "alone" / "results" / "cells").glob("*.json"))}
    assert {rt for enc, rt in got.values() if enc is not None} == {"torch"}, got
    assert {rt for enc, rt in got.values() if enc is None} == {None}, got

    by_key = run(bench_cli, tmp_path / "key", "--grid", study(tmp_path / "key", "pack_grafts = 6\n"))
    assert packs(by_key) == ["4"]
    assert "measured 8, resumed from store 0" in by_key.stdout  # mates: measured, not resumed
    assert records(tmp_path / "key") == unpacked

    again = run(bench_cli, tmp_path / "again", "--grid",
                study(tmp_path / "again", "pack_grafts = 2\n"), "--pack-grafts", "6")
    assert packs(again) == ["4"]  # the file alone: 2 + 2
    assert records(tmp_path / "again") == records(tmp_path / "key")
    assert pack_grafts(None, None, "local") == 1  # neither given: unpacked


def test_a_mate_already_recorded_is_resumed_not_packed(bench_cli, tmp_path):
    grid = study(tmp_path / "alone")
    run(bench_cli, tmp_path / "alone", "--grid", grid)
    unpacked = records(tmp_path / "alone")
    cells = tmp_path / "alone" / "results" / "cells"
    for path in cells.glob("*.json"):
        if path.stem != KEPT:
            path.unlink()
    kept = (cells / f"{KEPT}.json").read_bytes()
    resumed = run(bench_cli, tmp_path / "alone", "--grid", grid, "--pack-grafts", "4")
    assert packs(resumed) == ["3"]
    assert "measured 7, resumed from store 1" in resumed.stdout
    assert KEPT not in re.search(r"pack of 3 grafts[^\n]*", resumed.stdout).group(0)
    assert (cells / f"{KEPT}.json").read_bytes() == kept
    assert records(tmp_path / "alone") == unpacked


def test_a_mate_whose_training_fails_fails_alone_and_is_not_retrained(tiny_workspace):
    """Through the cell service: a pack of 3 whose dinov2_s mate sees NaN features (a planted
    feature transform): its failure record written, its case raising NonFiniteLoss at once when
    reached; the lead and the other mate measured, their outcomes "measured"."""
    profile = dataclasses.replace(TINY, protocol=TINY.protocol.replace(steps=4, eval_stride=30))
    ws = tiny_workspace(profile)
    lead, broken, mate = (CellSpec(GRAFT, "smolvla", "spatial", seed, encoder)
                          for encoder, seed in (("pixels", 0), ("dinov2_s", 0), ("pixels", 1)))

    def nan_features(features, frames):
        return {camera: torch.full_like(v, float("nan")) for camera, v in features.items()}

    settings = RunSettings(feature_dtype=ws.feature_dtype, pack_grafts=3)
    service = CellService(profile, ws.store, lambda: ws, settings,
                          feature_transform=lambda c: nan_features if c == broken else None,
                          pack_candidates=lambda cell: [lead, broken, mate])
    assert service.run(lead).cell_id == lead.id
    assert set(service.records) == {lead.id, mate.id}
    assert service.outcomes[lead.id] == service.outcomes[mate.id] == MEASURED
    assert "NonFiniteLoss" in service.outcomes[broken.id].reason
    assert ws.store.failure_path(broken.id).is_file() and ws.store.load(broken.id) is None
    with pytest.raises(NonFiniteLoss, match=rf"{broken.id}: .* \(packed with 2 other"):
        service.run(broken)  # the pack's error again: trained alone, it would not say "packed"
    assert service.run(mate) is service.records[mate.id]  # taken, not measured again


@pytest.mark.parametrize("args, says", [
    (["--pack-grafts", "0"], "--pack-grafts 0: give a whole number of grafts per backbone "
                             "pass >= 1, e.g. --pack-grafts 4"),
    (["--pack-grafts", "abc"], "--pack-grafts abc: not a whole number; give e.g. --pack-grafts 4"),
    (["--pack-grafts", "2", "--executor", "submitit-local"],
     "--pack-grafts 2 with --executor submitit-local: each array task measures one cell"),
])
def test_a_bad_pack_is_one_line_at_start_up(bench_cli, tmp_path, args, says):
    out = bench_cli(tmp_path, *GRID, *args)
    _one_line(out, says, tmp_path)


def test_a_bad_grid_key_is_one_line_at_start_up(bench_cli, tmp_path):
    study = tmp_path / "study.toml"
    study.write_text("pack_grafts = 0\n")
    _one_line(bench_cli(tmp_path, "--grid", str(study), *GRID),
              f"{study}: pack_grafts = 0: give a whole number of grafts per backbone pass >= 1",
              tmp_path)


def _one_line(out, says: str, folder) -> None:
    screen = out.stdout + out.stderr
    assert out.returncode == 4, screen
    assert says in screen and "Traceback" not in screen, screen
    lines = [line for line in screen.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("ERROR: "), screen
    assert not (folder / "results" / "cells").exists()
