"""Control cells against their references: wrapper neutrality and every control's delta.

delta = (control - reference) / reference, on mean MSE over the held-out windows, normalised and
raw. The wrapper-neutrality delta is this delta for native_wrapped against native.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Sequence

import numpy as np

from bench.records import CONTROL_KINDS, GRAFT

METRICS = ("normalized", "raw")


def relative_delta(value: float, reference: float) -> float:
    """(value - reference) / reference; NaN when the reference is 0 or not finite."""
    if not np.isfinite(reference) or reference == 0:
        return float("nan")
    return float((value - reference) / reference)


def find_reference(record: dict, records: Sequence[dict]) -> tuple[dict | None, str]:
    """The record a control is compared against, and the id looked for.

    Uses `record["reference"]`; without one, the graft cell of the same encoder and seed, or for
    native_wrapped / native-image controls the native cell (same seed if there is one)."""
    by_id = {r["cell_id"]: r for r in records}
    wanted = record.get("reference")
    if wanted:
        return by_id.get(wanted), wanted
    native_like = record["kind"] == "native_wrapped" or record.get("encoder") in (None, "native")
    kind = "native" if native_like else GRAFT
    candidates = [r for r in records
                  if r["kind"] == kind and r["backbone"] == record["backbone"]
                  and r["suite"] == record["suite"]
                  and (native_like or r["encoder"] == record["encoder"])]
    same_seed = [r for r in candidates if r["seed"] == record["seed"]]
    # The released policy does not depend on a cell seed: any seed's native cell will do.
    for r in same_seed or (candidates if native_like else []):
        return r, r["cell_id"]
    label = "native" if native_like else f"{record.get('encoder')} graft"
    return None, f"({label}, seed {record['seed']})"


@dataclass
class ControlDelta:
    cell_id: str
    kind: str
    backbone: str
    suite: str
    encoder: str | None
    variant: str | None
    seed: int
    reference_id: str
    reference_found: bool
    mse: dict[str, float]
    reference_mse: dict[str, float] = field(default_factory=dict)
    delta: dict[str, float] = field(default_factory=dict)

    @property
    def label(self) -> str:
        what = self.kind + (f"[{self.variant}]" if self.variant else "")
        return f"{what} of {self.encoder or 'native'}"


def control_deltas(records: Sequence[dict]) -> list[ControlDelta]:
    """One ControlDelta per control record (native_wrapped, lora, pooling, zero/shuffled image)."""
    out = []
    for r in sorted(records, key=lambda r: (r["backbone"], r["suite"], r["kind"], r["cell_id"])):
        if r["kind"] not in CONTROL_KINDS:
            continue
        ref, ref_id = find_reference(r, records)
        cd = ControlDelta(cell_id=r["cell_id"], kind=r["kind"], backbone=r["backbone"],
                          suite=r["suite"], encoder=r.get("encoder"), variant=r.get("variant"),
                          seed=int(r["seed"]), reference_id=ref_id,
                          reference_found=ref is not None,
                          mse={m: float(r["mse"][m]) for m in METRICS})
        if ref is not None:
            cd.reference_mse = {m: float(ref["mse"][m]) for m in METRICS}
            cd.delta = {m: relative_delta(cd.mse[m], cd.reference_mse[m]) for m in METRICS}
        out.append(cd)
    return out


@dataclass
class WrapperNeutrality:
    """(native_wrapped - native) / native on one backbone x suite, per seed and mean over seeds."""

    backbone: str
    suite: str
    per_seed: dict[int, dict[str, float]] = field(default_factory=dict)
    mean: dict[str, float] = field(default_factory=dict)
    unmatched: list[str] = field(default_factory=list)  # wrapped cells without a native record

    def to_dict(self) -> dict:
        return asdict(self)


def wrapper_neutrality(records: Sequence[dict]) -> dict[tuple[str, str], WrapperNeutrality]:
    """{(backbone, suite): WrapperNeutrality} from native_wrapped cells and their native refs."""
    out: dict[tuple[str, str], WrapperNeutrality] = {}
    for cd in control_deltas(records):
        if cd.kind != "native_wrapped":
            continue
        wn = out.setdefault((cd.backbone, cd.suite), WrapperNeutrality(cd.backbone, cd.suite))
        if cd.reference_found:
            wn.per_seed[cd.seed] = dict(cd.delta)
        else:
            wn.unmatched.append(f"{cd.cell_id} (reference {cd.reference_id} missing)")
    for wn in out.values():
        if wn.per_seed:
            wn.mean = {m: float(np.mean([d[m] for d in wn.per_seed.values()])) for m in METRICS}
    return out
