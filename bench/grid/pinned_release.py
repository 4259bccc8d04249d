"""Pinned releases: a tiny release's files committed with a study, loaded by content hash.

A tiny release trained on another machine is not the same release (studies/sim/REBUILD.md: other
CPU kernels, other rendered frames), and a long graft amplifies the difference past the gaps
between encoders. So a committed study names the release it was measured on, as a folder of
the files `save_pretrained` wrote, named `<backbone>-<content hash>`, in its grid file:

    [releases]
    pi05 = "releases/pi05-0123456789abcdef"   # relative to the grid file's folder

The folder's name is its claim: the content hash of its files must equal the name's last part,
checked when the grid file is read (start-up, exit 4) and again when the policy is loaded.
Records measured on it carry its weights' sha256 (the checkpoint `revision`), as records of a
cached release do, so a study's records resume on the pinned copy of their release.

    python -m bench.grid.pinned_release RELEASE_FOLDER --into studies/real/releases

copies a release folder (GRAFTBENCH_CACHE/released/<backbone>-<key>) there under its content
hash and prints the grid-file line. Standard library only: the grid file's start-up check must
not wait for torch.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import sys
from pathlib import Path

RELEASE_FILE = "graftbench_release.json"  # written by bench.resources.releases with the weights
HASH_CHARS = 16
_NAME = re.compile(rf"^(?P<backbone>.+)-(?P<hash>[0-9a-f]{{{HASH_CHARS}}})$")


def content_hash(folder: str | os.PathLike) -> str:
    """16 hex chars over every file under `folder`: its relative path and its bytes' sha256,
    in sorted path order (a renamed, added, removed or edited file changes it)."""
    root = Path(folder)
    outer = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        inner = hashlib.sha256(path.read_bytes()).hexdigest()
        outer.update(f"{path.relative_to(root).as_posix()}\0{inner}\n".encode())
    return outer.hexdigest()[:HASH_CHARS]


def check_pinned(backbone: str, folder: str | os.PathLike, where: str = "[releases]") -> Path:
    """The pinned release folder of `backbone`, checked: it exists, is named
    `<backbone>-<16 hex>`, holds a release of `backbone` and its content hash is its name's.
    ValueError (one line naming `where`, the value and the fix) otherwise."""
    path = Path(folder)
    given = f"{where} {backbone} = {str(folder)!r}"
    name = _NAME.match(path.name)
    if not path.is_dir():
        raise ValueError(f"{given}: no such folder; give a pinned release folder "
                         "(python -m bench.grid.pinned_release RELEASE --into DIR makes one)")
    if name is None or name["backbone"] != backbone:
        raise ValueError(f"{given}: the folder is not named {backbone}-<{HASH_CHARS} hex content "
                         "hash>; pin it with python -m bench.grid.pinned_release")
    try:
        meta = json.loads((path / RELEASE_FILE).read_text())
    except (OSError, ValueError):
        raise ValueError(f"{given}: no readable {RELEASE_FILE}; it is not a tiny release "
                         "folder (pin one from GRAFTBENCH_CACHE/released/)") from None
    if meta.get("backbone") != backbone:
        raise ValueError(f"{given}: it holds a release of {meta.get('backbone')!r}, not of "
                         f"{backbone!r}; name it under its own backbone")
    found = content_hash(path)
    if found != name["hash"]:
        raise ValueError(f"{given}: its files hash to {found}, not the {name['hash']} its name "
                         "claims (edited since it was pinned); restore it from git "
                         "(git checkout -- FOLDER) or pin the release again")
    return path


def pin(release: str | os.PathLike, into: str | os.PathLike) -> Path:
    """Copy the release folder `release` into `into`/<backbone>-<content hash> (atomically;
    an existing pin of the same content is kept); returns the pinned folder."""
    source = Path(release)
    backbone = json.loads((source / RELEASE_FILE).read_text())["backbone"]
    target = Path(into) / f"{backbone}-{content_hash(source)}"
    if target.is_dir():
        return check_pinned(backbone, target, "pinned")
    tmp = target.with_name(f".{target.name}.tmp{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(source, tmp, ignore=shutil.ignore_patterns("*.lock"))
    os.replace(tmp, target)
    return check_pinned(backbone, target, "pinned")


def main(argv: list[str] | None = None) -> None:
    """python -m bench.grid.pinned_release RELEASE_FOLDER --into DIR"""
    parser = argparse.ArgumentParser(prog="python -m bench.grid.pinned_release",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("release", help="a tiny release folder (GRAFTBENCH_CACHE/released/...)")
    parser.add_argument("--into", required=True, help="where pinned releases live, e.g. "
                        "studies/real/releases")
    args = parser.parse_args(argv)
    if not (Path(args.release) / RELEASE_FILE).is_file():
        print(f"python -m bench.grid.pinned_release: {args.release}: no {RELEASE_FILE}; give a "
              "tiny release folder (GRAFTBENCH_CACHE/released/<backbone>-<key>)", file=sys.stderr)
        raise SystemExit(4)
    into = Path(args.into)
    try:
        into.mkdir(parents=True, exist_ok=True)
        pinned = pin(args.release, into)
    except OSError as e:  # --into a file, or where this user cannot write
        print(f"python -m bench.grid.pinned_release: --into {args.into}: cannot pin there "
              f"({e.strerror or e}); give a folder you can write, e.g. studies/STUDY/releases",
              file=sys.stderr)
        raise SystemExit(4) from None
    # Paths in a grid file are read from its folder; a study keeps its releases beside it.
    print(f"pinned: {pinned}\nthe grid file's [releases] line, for a grid file in "
          f"{pinned.parent.parent}/ (paths are read from the grid file's folder): "
          f'{pinned.name.rsplit("-", 1)[0]} = "{pinned.parent.name}/{pinned.name}"')


if __name__ == "__main__":
    main()
