"""The results store: one JSON record per cell, written atomically; resume by protocol hash."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


class ResultsDirError(RuntimeError):
    pass


def atomic_write_json(path: Path, data: dict) -> None:
    """Temp file in the same folder + os.replace: a crash never leaves half a record."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=1, sort_keys=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


class ResultStore:
    """RESULTS_DIR/cells/<cell_id>.json (finished), RESULTS_DIR/failed/<cell_id>.json (last
    failure; never used to skip work), RESULTS_DIR/grid.json (the selected grid)."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)
        try:
            (self.root / "cells").mkdir(parents=True, exist_ok=True)
            (self.root / "failed").mkdir(parents=True, exist_ok=True)
            # A private probe file: xdist workers open the same store at the same moment, and a
            # shared name let one worker's unlink break another's (a false "not writable").
            fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=self.root)
            os.close(fd)
            os.unlink(probe)
        except OSError as e:
            raise ResultsDirError(
                f"results dir {self.root} is not writable ({e.strerror}); "
                "pass a writable folder with --results-dir PATH"
            ) from None

    def cell_path(self, cell_id: str) -> Path:
        return self.root / "cells" / f"{cell_id}.json"

    def load(self, cell_id: str) -> dict | None:
        path = self.cell_path(cell_id)
        if not path.exists():
            return None
        try:
            return json.loads(path.read_text())
        except json.JSONDecodeError:
            return None  # unreadable: treated as missing, recomputed

    def current(self, cell_id: str, protocol_hash: str) -> dict | None:
        """The stored record if it was measured under this protocol, else None."""
        record = self.load(cell_id)
        if record and record.get("status") == "ok" and record.get("protocol_hash") == protocol_hash:
            return record
        return None

    def write(self, record: dict) -> Path:
        path = self.cell_path(record["cell_id"])
        atomic_write_json(path, record)
        failed = self.root / "failed" / f"{record['cell_id']}.json"
        if failed.exists():
            failed.unlink()
        return path

    def write_failure(self, record: dict) -> Path:
        path = self.root / "failed" / f"{record['cell_id']}.json"
        atomic_write_json(path, {**record, "status": "failed"})
        return path

    def write_grid(self, expected: list[str], profile: str) -> None:
        atomic_write_json(self.root / "grid.json", {"expected": expected, "profile": profile})
