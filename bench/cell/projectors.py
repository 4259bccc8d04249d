"""Every projector-training cell keeps its trained projector: RESULTS_DIR/projectors/<cell_id>
.safetensors, float32, written atomically (temp file + rename), its sha256 in the record
(`projector_file` relative to the results dir, `projector_sha256`). bench.export reads it back
through `load_projector`, which refuses a file whose checksum is not the record's."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

PROJECTORS = "projectors"


class ProjectorFileError(RuntimeError):
    """A projector file absent or not the one its record names: one line with the fix."""


def projector_path(results_dir: str | os.PathLike, cell_id: str) -> Path:
    return Path(results_dir) / PROJECTORS / f"{cell_id}.safetensors"


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def save_projector(results_dir: str | os.PathLike, cell_id: str,
                   projector: torch.nn.Module) -> tuple[str, str]:
    """Write the projector's state (float32, CPU) for `cell_id`; (path relative to
    `results_dir`, sha256 of the file)."""
    path = projector_path(results_dir, cell_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().to("cpu", torch.float32).contiguous()
             for k, v in projector.state_dict().items()}
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        save_file(state, tmp)
        sha = file_sha256(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path.relative_to(results_dir).as_posix(), sha


def keep_for_session(folder: Path, record, projector: torch.nn.Module):
    """`record`'s trained projector saved in the session's folder, for a later cell of the run
    that takes it (bench.cell.plan `CellContext.keep_as`), with what its training recorded."""
    from bench.cell.plan import TrainedProjector

    path = Path(folder) / f"projector-{record.cell_id}.safetensors"
    save_file({k: v.detach().cpu().contiguous() for k, v in projector.state_dict().items()}, path)
    return TrainedProjector(path, record.training.loss_curve, record.training.probe_loss,
                            record.cell_id)


def load_projector(results_dir: str | os.PathLike, cell_id: str, relative: str | None,
                   sha256: str | None) -> dict[str, torch.Tensor]:
    """The state dict a record names, checked against its sha256; ProjectorFileError else."""
    rerun = (f"run the cell again to keep its projector (pytest bench -k {cell_id} "
             f"--results-dir {results_dir} --rerun)")
    if not relative or not sha256:
        raise ProjectorFileError(f"cell {cell_id} names no projector file (recorded before "
                                 f"projectors were kept): {rerun}")
    path = Path(results_dir) / relative
    if not path.is_file():
        raise ProjectorFileError(f"projector file {path} of cell {cell_id} is missing: {rerun}")
    found = file_sha256(path)
    if found != sha256:
        raise ProjectorFileError(f"projector file {path} has sha256 {found[:12]}..., the record "
                                 f"of {cell_id} says {sha256[:12]}...: the file was changed; "
                                 f"{rerun}")
    return load_file(str(path))
