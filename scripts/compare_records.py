"""Compare the records of two results dirs: their measurements must be the same bits.

usage: python compare_records.py BEFORE_DIR AFTER_DIR
Measurement fields (must be identical, float by float): mse, per_window, per_task, per_horizon,
window_ids. Also reports: key sets that differ, and which other fields differ (times, dates,
commit ids, hardware line are expected to)."""

import json
import struct
import sys
from pathlib import Path

MEASURED = ("mse", "per_window", "per_task", "per_horizon", "window_ids", "n_windows")


def bits(x):
    """Every float as its IEEE-754 bytes, recursively: equality of bits, NaN included."""
    if isinstance(x, float):
        return struct.pack("<d", x).hex()
    if isinstance(x, dict):
        return {k: bits(v) for k, v in x.items()}
    if isinstance(x, list):
        return [bits(v) for v in x]
    return x


def main(before: Path, after: Path) -> int:
    b = {p.stem: json.loads(p.read_text()) for p in sorted((before / "cells").glob("*.json"))}
    a = {p.stem: json.loads(p.read_text()) for p in sorted((after / "cells").glob("*.json"))}
    print(f"cells: before {len(b)}, after {len(a)}, in both {len(set(a) & set(b))}")
    for cid in sorted(set(a) ^ set(b)):
        print(f"  only in {'before' if cid in b else 'after'}: {cid}")
    bad, other, keys_only = 0, {}, {}
    for cid in sorted(set(a) & set(b)):
        rb, ra = b[cid], a[cid]
        diff = [k for k in MEASURED if bits(rb.get(k)) != bits(ra.get(k))]
        if diff:
            bad += 1
            print(f"  MEASUREMENTS DIFFER {cid}: {diff}")
        for k in set(rb) ^ set(ra):
            side = "before" if k in rb else "after"
            keys_only[(k, side)] = keys_only.get((k, side), 0) + 1
        for k in set(rb) & set(ra):
            if k not in MEASURED and bits(rb[k]) != bits(ra[k]):
                other[k] = other.get(k, 0) + 1
    n = len(set(a) & set(b))
    print(f"measurements identical to the bit (mse normalised+raw, per_window, per_task, "
          f"per_horizon, window_ids, n_windows): {n - bad} of {n} cells")
    print("keys present on one side only (cells): " + (", ".join(
        f"{k} only {side} {v}" for (k, side), v in sorted(keys_only.items())) or "none"))
    print("other fields that differ (cells): " + ", ".join(f"{k} {v}" for k, v in sorted(other.items())))
    return 1 if bad or set(a) ^ set(b) else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2])))
