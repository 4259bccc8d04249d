"""A robustness case beside its graft cell, in one process (docs/PERFORMANCE.md).

Measures the tiny protocol's BACKBONE-spatial-pixels-seed0 graft cell, then its robustness case
with all 21 perturbations (rerun, the perturbed features already stored) two ways, alternating:
one scoring pass per perturbation (the first implementation) and one pass for all (the current
`_Scorer.entries`); prints the best of two of each and its ratio to the cell, twice.

    OMP_NUM_THREADS=1 python scripts/robust_cost.py smolvla
"""

from __future__ import annotations

import sys
import tempfile
import time

import torch

from bench.grid.cells import CellSpec
from bench.grid.protocol import TINY
from bench.progress import QUIET
from bench.results.store import ResultStore
from bench.robust import rescore as robust
from bench.robust.perturbations import parse_robustness
from bench.cell.service import run_cell
from bench.resources.workspace import Workspace


def main(backbone: str) -> None:
    torch.set_num_threads(1)
    ws = Workspace(TINY, ResultStore(tempfile.mkdtemp()), progress=QUIET)
    spec = CellSpec("graft", backbone, "spatial", 0, "pixels")
    ws.suite("spatial"), ws.backbone(backbone, "spatial")
    everything = parse_robustness(["all"], "robust_cost")
    one_pass = robust._Scorer.entries

    def per_perturbation(self, perturbations):
        return [one_pass(self, [a])[0] for a in perturbations]

    for rep in range(2):
        t = time.perf_counter()
        run_cell(spec, ws)
        cell = time.perf_counter() - t
        if rep == 0:  # the perturbed windows' features, built once
            robust.measure_robust(spec, ws, everything, rerun=True)
        times: dict[str, list[float]] = {}
        for name, way in (("per perturbation", per_perturbation), ("one pass", one_pass)) * 2:
            robust._Scorer.entries = way
            t = time.perf_counter()
            robust.measure_robust(spec, ws, everything, rerun=True)
            times.setdefault(name, []).append(time.perf_counter() - t)
        robust._Scorer.entries = one_pass
        print(f"{backbone}: cell {cell:.2f} s; " + "; ".join(
            f"case {name} {min(v):.2f} s ({min(v) / cell:.1%})" for name, v in times.items()),
            flush=True)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "smolvla")
