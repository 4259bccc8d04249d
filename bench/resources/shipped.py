"""Tiny releases shipped with graftbench, so that a first run loads them instead of training them.

The offline world trains each tiny released policy natively on first use (1,500 steps, ~1 min a
backbone on one core), before any cell can run. The releases of the default recipe (the tiny
profiles' protocol on the generated suites) are shipped instead, under bench/resources/shipped/,
in the pinned form of bench.grid.pinned_release: a folder named `<backbone>-<content hash>`
whose files (safetensors weights and stats, configs) are sha256-checked against that name
before use. shipped/index.json maps the release key their recipe trains (the cache folder's name,
bench.resources.releases.release_key: backbone, data fingerprints, architecture, native
protocol, release index) to that folder. A run whose key is shipped copies it into its cache,
checked again, and loads it from there as if it had trained it; any other recipe trains.

They were trained here, with one torch thread, on AMD EPYC (AVX-512 kernels): the weights a run
with one torch thread (each xdist worker's) trains on that machine, bit for bit. Another
machine's kernels train other bits (studies/sim/REBUILD.md); the shipped copy gives every machine
the same release. A recipe change (another key) makes the default run train again, and
tests/test_shipped_releases.py fail, until its releases are shipped anew:

    python -m bench.resources.shipped GRAFTBENCH_CACHE/released/<backbone>-<key>

pins that folder here and enters it in the index.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from bench.grid.pinned_release import RELEASE_FILE, check_pinned, content_hash, pin

SHIPPED_DIR = Path(__file__).with_name("shipped")
# {the cache folder a recipe trains (<backbone>-<release key>): its shipped, pinned folder}, one
# entry per shipped release (the default grid's two, and the tests' third backbone's).
INDEX = "index.json"


def shipped() -> dict[str, str]:
    """The index: cache folder name -> shipped folder name."""
    return json.loads((SHIPPED_DIR / INDEX).read_text())


def shipped_release(cache_name: str) -> Path | None:
    """The shipped folder standing for the cache folder `cache_name` (None: none shipped),
    its content hash checked (ValueError naming the fix if its files were changed)."""
    pinned = shipped().get(cache_name)
    if pinned is None:
        return None
    backbone = cache_name.rsplit("-", 1)[0]
    return check_pinned(backbone, SHIPPED_DIR / pinned, f"shipped release of {cache_name}:")


def install_shipped(shipped: Path, folder: Path) -> None:
    """Copy the shipped release `shipped` to the cache folder `folder` (atomically; the copy's
    content hash checked against the shipped folder's name before it takes the name)."""
    tmp = folder.with_name(f"{folder.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(shipped, tmp)
    expected = shipped.name.rsplit("-", 1)[1]
    if content_hash(tmp) != expected:
        shutil.rmtree(tmp, ignore_errors=True)
        raise OSError(f"copying {shipped} to {folder} changed its files (content hash is not "
                      f"{expected}); check the disk under {folder.parent}")
    os.replace(tmp, folder)


def main(argv: list[str] | None = None) -> None:
    """python -m bench.resources.shipped RELEASE_FOLDER"""
    parser = argparse.ArgumentParser(prog="python -m bench.resources.shipped",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("release", help="a tiny release folder of the cache "
                        "(GRAFTBENCH_CACHE/released/<backbone>-<key>)")
    args = parser.parse_args(argv)
    source = Path(args.release)
    if not (source / RELEASE_FILE).is_file():
        print(f"python -m bench.resources.shipped: {source}: no {RELEASE_FILE}; give a tiny "
              "release folder (GRAFTBENCH_CACHE/released/<backbone>-<key>)", file=sys.stderr)
        raise SystemExit(4)
    pinned = pin(source, SHIPPED_DIR)
    index = {**shipped(), source.name: pinned.name}
    (SHIPPED_DIR / INDEX).write_text(json.dumps(dict(sorted(index.items())), indent=1) + "\n")
    print(f"shipped: {pinned}, for {source.name} (in {SHIPPED_DIR / INDEX})")


if __name__ == "__main__":
    main()
