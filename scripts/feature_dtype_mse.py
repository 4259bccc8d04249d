"""How far the half-precision feature stores move tiny cells' MSEs from a float32 store.

    HF_HUB_OFFLINE=1 OMP_NUM_THREADS=1 .venv/bin/python scripts/feature_dtype_mse.py \
        [--dtypes float32,fp16,bf16] [--cells pi05:pixels,pi05:dinov2_s,smolvla:siglip,...]

Each cell (graft, spatial, seed 0; "BACKBONE:ENCODER" or "BACKBONE:ENCODER:pool_VARIANT") runs
through bench.cell.service.run_cell once per dtype, each dtype with its own fresh feature store and
results store in a temporary folder (released checkpoints and suites come from the usual cache).
Prints per cell the relative change of the normalised and raw MSE of each dtype against the
first, then the maxima; docs/PERFORMANCE.md ("The feature store") has the measured figures.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench.progress import QUIET
from bench.grid.cells import CellSpec  # noqa: E402
from bench.resources.features import FeatureStore  # noqa: E402
from bench.grid.protocol import TINY  # noqa: E402
from bench.cell.service import run_cell  # noqa: E402
from bench.results.store import ResultStore  # noqa: E402
from bench.resources.workspace import Workspace  # noqa: E402

DEFAULT_CELLS = ("pi05:pixels,pi05:blind,pi05:dinov2_s,pi05:siglip,pi05:fastvit,"
                 "pi05:dinov2_s:pool_double,pi05:pixels:pool_half,"
                 "smolvla:pixels,smolvla:dinov2_s,smolvla:siglip")


def cell_of(text: str) -> CellSpec:
    backbone, encoder, *variant = text.split(":")
    if variant:
        return CellSpec("pooling", backbone, "spatial", 0, encoder,
                        variant[0].removeprefix("pool_"))
    return CellSpec("graft", backbone, "spatial", 0, encoder)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dtypes", default="float32,fp16,bf16")
    parser.add_argument("--cells", default=DEFAULT_CELLS)
    args = parser.parse_args()
    dtypes, cells = args.dtypes.split(","), [cell_of(c) for c in args.cells.split(",")]
    tmp = Path(tempfile.mkdtemp(prefix="graftbench-dtype-mse-"))
    ws = Workspace(TINY, ResultStore(tmp / "results-init"), progress=QUIET)
    mse: dict[str, dict[str, dict]] = {}
    for dtype in dtypes:
        ws.store = ResultStore(tmp / f"results-{dtype}")
        ws.feature_dtype = dtype
        ws._features = FeatureStore(tmp / f"features-{dtype}", dtype=dtype, progress=QUIET)
        for cell in cells:
            mse.setdefault(cell.id, {})[dtype] = run_cell(cell, ws).scores.mse
            print(f"{dtype:8} {cell.id}: {mse[cell.id][dtype]}", flush=True)
    ref, worst = dtypes[0], {d: 0.0 for d in dtypes[1:]}
    print(f"\nrelative MSE change against {ref} (normalised / raw):")
    for cell_id, by_dtype in mse.items():
        parts = []
        for dtype in dtypes[1:]:
            rel = [abs(by_dtype[dtype][k] - by_dtype[ref][k]) / abs(by_dtype[ref][k])
                   for k in ("normalized", "raw")]
            worst[dtype] = max(worst[dtype], *rel)
            parts.append(f"{dtype} {rel[0]:.2e} / {rel[1]:.2e}")
        print(f"  {cell_id:45} " + "   ".join(parts))
    print("max: " + ", ".join(f"{d} {w:.2e}" for d, w in worst.items()))


if __name__ == "__main__":
    main()
