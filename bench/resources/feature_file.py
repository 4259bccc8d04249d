"""The on-disk format of stored features: one file per (encoder, suite, stored grid, dtype), built
chunk by chunk, read back per batch with positioned reads. This module is its only owner.

A completed file `<key>.feat` (little-endian):

    [camera 0: N frames x T tokens x C channels] [camera 1: ...] ...   the data, camera-major
    [footer: UTF-8 JSON manifest] [footer length: uint64] [MAGIC: 8 bytes]

Camera-major, so that each chunk of frames is one write per camera at a known offset and one
frame of one camera is one contiguous record (T x C values). Values are stored as `dtype`:
"float32" (the encoder's numbers bit for bit), "fp16" or "bf16" (written and read as 16-bit
integers through torch views: numpy has no bfloat16). Reads return float32.

Building is crash-safe and resumable:

    <key>.feat.partial        the data, written with pwrite (sparse until written)
    <key>.feat.partial.json   progress: frames committed, each chunk's crc32 per camera; replaced
                              atomically (write, fsync, rename) after the chunk's data is fsynced
    <key>.feat.lock           flock held while building (two xdist workers never write one file)

A killed build leaves only those. The rerun checks the committed chunks against their crc32,
continues after the last good one, appends the footer, fsyncs and renames the file to
`<key>.feat`. `StoredFeatures.open` reads only that name and checks the footer (magic, key,
layout, size) before trusting it; `verify()` also checks every chunk's crc32.

Memory: nothing here scales with the number of frames. The writer holds one chunk; a read
allocates its batch. No memory map is used, because the pages of a map that a process touches
count towards its resident set (and it would then grow with the frames read).
"""

from __future__ import annotations

import json
import os
import shutil
import struct
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ondisk.filelock import exclusive

FORMAT = "graftbench-features/1"
MAGIC = b"GBFEAT01"
TAIL = struct.Struct("<Q8s")  # footer length, MAGIC
DTYPES = {"float32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}
_BITS = {torch.float32: torch.int32, torch.float16: torch.int16, torch.bfloat16: torch.int16}
DISK_MARGIN = 512 * 2**20  # bytes a build leaves free beyond its own file
# Batches of at least this many bytes are read with READ_THREADS reads in flight: cold random
# reads of a batch-32 pi0.5 SigLIP batch (19 MB) went from 41 to 15 ms here (469 -> 1264 MB/s).
PARALLEL_READ_BYTES = 2**20
READ_THREADS = 8
GB = 1e9


class StoreDoesNotFit(RuntimeError):
    """A store that would not fit on disk: refused before anything is written."""


class StoreInvalid(RuntimeError):
    """A completed file whose footer does not match what the caller expects (never read)."""


@dataclass(frozen=True)
class Layout:
    """What a file holds: the key it was built for and the shape of each camera's array."""

    key: str
    cameras: tuple[str, ...]
    frames: int
    grid: tuple[int, int]  # (rows, cols) of the stored tokens, row-major
    channels: int
    dtype: str  # a key of DTYPES
    # How the encoder laid its (B, C, h, w) grid out in memory: "nchw" or "nhwc" (ViT tokens
    # reshaped to a grid are channels-last views). Readers rebuild the same strides: pooling a
    # channels-last grid sums in another order, and float32 must give the encoder's numbers.
    memory_format: str = "nchw"

    @property
    def tokens(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def itemsize(self) -> int:
        return DTYPES[self.dtype].itemsize

    @property
    def record_bytes(self) -> int:
        """One frame of one camera."""
        return self.tokens * self.channels * self.itemsize

    @property
    def data_bytes(self) -> int:
        return len(self.cameras) * self.frames * self.record_bytes

    def offset(self, camera: int, frame: int) -> int:
        return (camera * self.frames + frame) * self.record_bytes

    def to_json(self) -> dict:
        d = asdict(self)
        return {**d, "cameras": list(self.cameras), "grid": list(self.grid)}

    @classmethod
    def from_json(cls, d: dict) -> "Layout":
        return cls(d["key"], tuple(d["cameras"]), int(d["frames"]), tuple(d["grid"]),
                   int(d["channels"]), d["dtype"], d["memory_format"])


def partial_path(path: Path) -> Path:
    return path.with_name(path.name + ".partial")


def progress_path(path: Path) -> Path:
    return path.with_name(path.name + ".partial.json")


def _as_bits(x: Tensor, dtype: str) -> np.ndarray:
    """(n, T, C) float32 -> the stored bytes as a numpy integer array (same shape)."""
    stored = x.to(DTYPES[dtype]).contiguous()
    if dtype == "fp16" and not torch.isfinite(stored).all() and torch.isfinite(x).all():
        raise ValueError(f"features reach {float(x.abs().max()):.4g}, beyond fp16's range "
                         "(65504): store them as bf16 or float32 (Workspace.feature_dtype)")
    return stored.view(_BITS[stored.dtype]).numpy()


def _pread_into(fd: int, buf: memoryview, offset: int) -> None:
    """Fill `buf` from `offset`, looping over short reads; EOF before the end is an error."""
    done = 0
    while done < len(buf):
        n = os.preadv(fd, [buf[done:]], offset + done)
        if n == 0:
            raise StoreInvalid(f"file ends at byte {offset + done}, expected {offset + len(buf)}")
        done += n


def _pwrite_all(fd: int, data: memoryview, offset: int) -> None:
    done = 0
    while done < len(data):
        done += os.pwrite(fd, data[done:], offset + done)


def _fsync_replace(path: Path, text: str) -> None:
    """Write `text` to `path` atomically and durably (tmp, fsync, rename, fsync the folder)."""
    tmp = path.with_name(path.name + f".tmp-{os.getpid()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_POOL: tuple[int, ThreadPoolExecutor] | None = None  # (pid that made it, pool)


def _read_pool() -> ThreadPoolExecutor:
    """Threads that only wait on preads (which release the GIL); no torch work runs on them.
    Made again in a forked child, whose copy of the pool has no live threads."""
    global _POOL
    if _POOL is None or _POOL[0] != os.getpid():
        pool = ThreadPoolExecutor(READ_THREADS, thread_name_prefix="graftbench-read")
        _POOL = (os.getpid(), pool)
    return _POOL[1]


class StoredFeatures:
    """A completed file, opened once: `read(camera, frames)` -> (B, T, C) float32 on the CPU."""

    def __init__(self, path: Path, layout: Layout, manifest: dict, fd: int):
        self.path, self.layout, self.manifest, self._fd = path, layout, manifest, fd

    @classmethod
    def open(cls, path: str | os.PathLike, expect: Layout | None = None) -> "StoredFeatures":
        """Open a completed file; StoreInvalid when its footer is missing, torn or not `expect`."""
        path = Path(path)
        fd = os.open(path, os.O_RDONLY)
        try:
            size = os.fstat(fd).st_size
            tail = bytearray(TAIL.size)
            if size < TAIL.size:
                raise StoreInvalid(f"{path}: {size} bytes, too short for a footer")
            _pread_into(fd, memoryview(tail), size - TAIL.size)
            length, magic = TAIL.unpack(tail)
            if magic != MAGIC or length > size - TAIL.size:
                raise StoreInvalid(f"{path}: no {MAGIC!r} footer (not a completed store)")
            footer = bytearray(length)
            _pread_into(fd, memoryview(footer), size - TAIL.size - length)
            try:
                manifest = json.loads(footer)
                layout = Layout.from_json(manifest["layout"])
            except (ValueError, KeyError, TypeError) as e:
                raise StoreInvalid(f"{path}: unreadable footer ({e})") from None
            if manifest.get("format") != FORMAT:
                raise StoreInvalid(f"{path}: format {manifest.get('format')!r}, not {FORMAT!r}")
            if expect is not None and layout != expect:
                raise StoreInvalid(f"{path}: holds {layout}, expected {expect}")
            if size != layout.data_bytes + length + TAIL.size:
                raise StoreInvalid(f"{path}: {size} bytes, layout says "
                                   f"{layout.data_bytes + length + TAIL.size}")
        except BaseException:
            os.close(fd)
            raise
        return cls(path, layout, manifest, fd)

    def read(self, camera: int, frames: np.ndarray) -> Tensor:
        """Frames (B,) of camera index `camera` -> (B, T, C) float32 (a fresh tensor)."""
        lay = self.layout
        frames = np.asarray(frames, dtype=np.int64).reshape(-1)
        if len(frames) and (frames.min() < 0 or frames.max() >= lay.frames):
            raise IndexError(f"frames {frames.min()}..{frames.max()} outside 0..{lay.frames - 1}"
                             f" of {self.path.name}")
        stored = torch.empty((len(frames), lay.tokens, lay.channels), dtype=DTYPES[lay.dtype])
        rows = memoryview(stored.view(_BITS[stored.dtype]).numpy()).cast("B")
        rec, starts = lay.record_bytes, [lay.offset(camera, f) for f in frames.tolist()]

        def read_rows(part: range) -> None:
            for i in part:
                _pread_into(self._fd, rows[i * rec:(i + 1) * rec], starts[i])

        if len(frames) * rec < PARALLEL_READ_BYTES:
            read_rows(range(len(frames)))
        else:  # several reads in flight: a disk serves random reads faster at depth
            parts = [range(k, len(frames), READ_THREADS) for k in range(READ_THREADS)]
            list(_read_pool().map(read_rows, parts))
        return stored.float()

    def verify(self) -> None:
        """Check every chunk's crc32 (reads the whole file); StoreInvalid on a mismatch."""
        bad = _bad_chunk(self._fd, self.layout, self.manifest["chunk_frames"],
                         self.manifest["crc32"])
        if bad is not None:
            raise StoreInvalid(f"{self.path}: chunk {bad} does not match its crc32")

    def close(self, _close=os.close) -> None:  # os.close bound early: __del__ at exit
        if getattr(self, "_fd", -1) >= 0:
            _close(self._fd)
            self._fd = -1

    def __del__(self):
        self.close()


def _chunk_crcs(fd: int, layout: Layout, start: int, stop: int) -> list[int]:
    crcs = []
    for cam in range(len(layout.cameras)):
        buf = bytearray((stop - start) * layout.record_bytes)
        _pread_into(fd, memoryview(buf), layout.offset(cam, start))
        crcs.append(zlib.crc32(buf))
    return crcs


def _bad_chunk(fd: int, layout: Layout, chunk_frames: int, crcs: list) -> int | None:
    """Index of the first chunk whose data does not match its crc32 (None: all match)."""
    for i, expected in enumerate(crcs):
        start = i * chunk_frames
        stop = min(start + chunk_frames, layout.frames)
        if _chunk_crcs(fd, layout, start, stop) != expected:
            return i
    return None


# compute(start, stop) -> {camera: (stop - start, T, C) float32}
ComputeChunk = Callable[[int, int], dict[str, Tensor]]


def preflight(path: Path, layout: Layout, done_frames: int, chunk_frames: int,
              say: Callable[[str], None]) -> None:
    """Print the size the build takes and the free disk; StoreDoesNotFit (one line) if short.
    RAM is not checked: a build holds one chunk, whatever the number of frames."""
    total = layout.data_bytes
    left = total - done_frames * len(layout.cameras) * layout.record_bytes
    free = shutil.disk_usage(path.parent).free
    chunk = chunk_frames * len(layout.cameras) * layout.tokens * layout.channels * 4
    say(f"{layout.dtype} {layout.grid[0]}x{layout.grid[1]}x{layout.channels}, "
        f"{len(layout.cameras)} cameras x {layout.frames} frames: {total / GB:.2f} GB on disk "
        f"({left / GB:.2f} GB still to write), {free / GB:.1f} GB free in {path.parent}; "
        f"RAM: one chunk of {chunk_frames} frames ({chunk / 1e6:.0f} MB float32)")
    if left + DISK_MARGIN > free:
        raise StoreDoesNotFit(
            f"feature store {path.name} needs {left / GB:.2f} GB more on disk, {free / GB:.2f} GB "
            f"free in {path.parent}: free space, point GRAFTBENCH_CACHE at a larger disk, or run "
            "with --features loop (no store)")


def _resume_point(fd: int, layout: Layout, chunk_frames: int, progress: Path) -> list:
    """The committed chunks' crc32 lists that still match the data (empty: start over)."""
    try:
        state = json.loads(progress.read_text())
        same = (state["format"] == FORMAT and state["chunk_frames"] == chunk_frames
                and Layout.from_json(state["layout"]) == layout)
        crcs = list(state["crc32"]) if same else []
    except (OSError, ValueError, KeyError, TypeError):  # none yet, torn or another format
        return []
    bad = _bad_chunk(fd, layout, chunk_frames, crcs)
    return crcs if bad is None else crcs[:bad]


def build(path: str | os.PathLike, layout: Layout, compute: ComputeChunk, chunk_frames: int,
          say: Callable[[str], None] = lambda s: None,
          chunk_done: Callable[[int, int], None] | None = None) -> StoredFeatures:
    """Build (or resume, or find finished by another process) the file `path`, then open it.

    `compute(start, stop)` gives frames [start, stop) of every camera; it is called only for
    chunks not yet committed. `chunk_done(frames_done, frames_total)` runs after each commit
    (progress bars; tests stop a build there)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with exclusive(path.with_name(path.name + ".lock")):  # the kernel frees it if we die
        if not path.exists():
            _build_locked(path, layout, compute, chunk_frames, say, chunk_done)
    return StoredFeatures.open(path, expect=layout)


def _build_locked(path: Path, layout: Layout, compute: ComputeChunk, chunk_frames: int,
                  say, chunk_done) -> None:
    part, progress = partial_path(path), progress_path(path)
    fd = os.open(part, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        crcs = _resume_point(fd, layout, chunk_frames, progress)
        done = min(len(crcs) * chunk_frames, layout.frames)
        preflight(path, layout, done, chunk_frames, say)
        if done:
            say(f"resuming after {done} of {layout.frames} frames (committed chunks checked)")
        os.ftruncate(fd, layout.data_bytes)  # sparse: blocks are taken as chunks are written
        t0 = time.monotonic()
        while done < layout.frames:
            stop = min(done + chunk_frames, layout.frames)
            chunk = compute(done, stop)
            crcs.append(_write_chunk(fd, layout, chunk, done, stop))
            os.fsync(fd)  # the data is durable before the progress file says it is there
            _fsync_replace(progress, json.dumps({"format": FORMAT, "layout": layout.to_json(),
                                                 "chunk_frames": chunk_frames, "crc32": crcs}))
            done = stop
            if chunk_done is not None:
                chunk_done(done, layout.frames)
        footer = json.dumps({"format": FORMAT, "layout": layout.to_json(),
                             "chunk_frames": chunk_frames, "crc32": crcs,
                             "build_s": round(time.monotonic() - t0, 3)}).encode()
        _pwrite_all(fd, memoryview(footer + TAIL.pack(len(footer), MAGIC)), layout.data_bytes)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(part, path)  # the one step that makes the file visible to readers
    _fsync_dir(path.parent)
    progress.unlink(missing_ok=True)


def _write_chunk(fd: int, layout: Layout, chunk: dict[str, Tensor], start: int,
                 stop: int) -> list[int]:
    """Write frames [start, stop) of every camera; their crc32 per camera."""
    crcs = []
    expected = (stop - start, layout.tokens, layout.channels)
    for cam, camera in enumerate(layout.cameras):
        x = chunk[camera].detach().to("cpu", torch.float32)
        if tuple(x.shape) != expected:
            raise ValueError(f"camera {camera!r}: chunk of shape {tuple(x.shape)}, "
                             f"expected {expected}")
        data = memoryview(_as_bits(x, layout.dtype)).cast("B")
        _pwrite_all(fd, data, layout.offset(cam, start))
        crcs.append(zlib.crc32(data))
    return crcs
