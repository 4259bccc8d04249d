"""Pooled encoder features: the encoder's grid pooled to the backbone's token grid, either in the
loop (`encode_pooled`) or from a feature store built once per (encoder, suite).

`encode_pooled` is the one function that turns images into pooled features. The store keeps the
encoder's own output grid (before pooling) and `PooledView` pools it per batch with the same
`pool_grid`, so a float32 store gives the pre-store cache's numbers bit for bit.

Which grid is stored: always the encoder's own (h, w), one file per (encoder, suite, dtype),
whatever grid a cell asks for.
- Coarser targets (SmolVLA's 8x8 from SigLIP's 14x14, pool_half, pool_global) are pooled from it
  per batch, as `encode_pooled` pools the encoder's output.
- Finer targets (pool_double, and pi0.5's 16x16 from SigLIP-B/16's 14x14) need more tokens than
  the encoder gives. Adaptive pooling to a finer grid repeats cells and averages neighbours: a
  fixed linear map of the encoder grid, so a file at the finer grid would hold no information
  the encoder grid lacks, at up to 5x the bytes (32x32 vs 14x14). The encoder grid is stored and
  mapped per batch.
- When the encoder's grid is finer than every grid a session asks for, a file at the largest
  target would be smaller. We still store the encoder grid: one extraction pass serves every
  backbone and pooling variant, and a cell's numbers never depend on which other cells a session
  ran. On the paper grid it costs no disk: pi0.5's 16x16 asks for at least as many tokens as
  each paper encoder gives. The preflight line prints the size before anything is written.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Callable, Protocol

import torch
from torch import Tensor

from bench.loops.encode import encode_grid
from bench.resources import extraction
from bench.resources import feature_file as fs
from bench.progress import Progress, say
from encoders.base import Encoder
from graftcore.graft import pool_grid  # noqa: F401  (the one pooling, shared with the plugin)

# Bump when a change to pooling, encoding or storage moves stored numbers on purpose.
# 2: the store keeps the encoder's own grid (pooled per batch), in Workspace.feature_dtype.
FEATURES_VERSION = "2"
CHUNK_FRAMES = 64  # frames encoded (and committed to disk) at a time

# transform(features {camera: (B, T, C) float32}, frames (B,) global indices) -> same shapes;
# applied to each batch read, one camera at a time (bench.cell.plan.CellContext.feature_transform)
FeatureTransform = Callable[[dict, Tensor], dict]


class FeatureSource(Protocol):
    """What the store needs of a suite (bench.suites.base.Suite satisfies it)."""

    name: str
    fingerprint: str
    camera_keys: tuple[str, ...]
    state: Tensor  # (N, 8): only its length (the number of frames) is used here

    def images(self, frames: Tensor) -> dict[str, Tensor]: ...


def feature_key(encoder: Encoder, suite: FeatureSource, grid: tuple[int, int] | None,
                dtype: str = "float32", runtime: str = "torch") -> str:
    """sha256 over everything that changes the stored numbers (grid: the stored one; runtime:
    "torch" or an extraction.onnx_tag(), named only when not torch so torch's keys never move)."""
    spec = encoder.spec
    fields = {
        "encoder": spec.name,
        "timm_name": spec.timm_name,
        "weights_id": encoder.weights_id,
        "input_size": getattr(encoder, "input_size", spec.input_size),
        "mean": list(spec.mean),
        "std": list(spec.std),
        "num_prefix_tokens": spec.num_prefix_tokens,
        "grid": list(grid) if grid is not None else None,
        "dtype": dtype,
        "suite": suite.fingerprint,
        "cameras": list(suite.camera_keys),
        "version": FEATURES_VERSION,
    }
    if encoder.weights_id.startswith("tiny"):  # tiny architecture is defined by its overrides
        fields["tiny_kwargs"] = repr(sorted(spec.tiny_kwargs.items()))
    if runtime != "torch":  # another runtime's kernels: other float32 bits (bench.resources.extraction)
        fields["runtime"] = runtime
    blob = json.dumps(fields, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()


class PooledView:
    """One camera of a stored file as the runner indexes it: `view[frames]` reads those frames,
    pools them to `grid` and applies the transform -> (B, rows*cols, C) float32 on the CPU.
    `.shape` is (N_frames, rows*cols, C) as if the whole pooled array were in memory.

    A float32 store pools in the memory format the encoder returned (torch's NCHW and NHWC
    kernels sum in different orders: that is what makes it bit-identical). Half stores always
    pool channels-last, the CPU kernel that vectorises over channels (a batch of 32 14x14x768
    grids to 16x16: 14 ms, against 303 ms for NCHW, here); that moves results by float32
    summation order only (~1e-7), far below the storage rounding."""

    def __init__(self, stored: fs.StoredFeatures, camera: str, grid: tuple[int, int],
                 transform: FeatureTransform | None = None, runtime: str | None = None):
        lay = stored.layout
        self.stored, self.camera, self.grid, self.transform = stored, camera, grid, transform
        self.runtime = runtime  # what extracted the file: "torch" or an onnxruntime tag
        self._index = lay.cameras.index(camera)
        self.shape = torch.Size((lay.frames, grid[0] * grid[1], lay.channels))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, frames) -> Tensor:
        index = torch.as_tensor(frames, dtype=torch.long)
        flat = index.reshape(-1)
        lay = self.stored.layout
        tokens = self.stored.read(self._index, flat.numpy())  # (B, h*w, C)
        grid = tokens.transpose(1, 2).reshape(len(flat), lay.channels, *lay.grid)  # NHWC view
        if lay.dtype == "float32" and lay.memory_format == "nchw":
            grid = grid.contiguous()
        pooled = pool_grid(grid, self.grid).contiguous()
        if self.transform is not None:
            pooled = self.transform({self.camera: pooled}, flat)[self.camera]
        return pooled.reshape(*index.shape, *pooled.shape[1:])


def feature_runtime(views: dict | None) -> str | None:
    """The runtime that extracted stored feature `views` ({camera: PooledView}): "torch" or an
    extraction.onnx_tag(); None for no store (the encoder in the loop) or views that do not say
    (in-memory arrays)."""
    tags = {getattr(v, "runtime", None) for v in (views or {}).values()}
    return tags.pop() if len(tags) == 1 else None


class FeatureStore:
    """The session's stored features under `root`: each file built once (resumably), opened once
    and kept open, shared by every cell that reads it. `runtime`: what extracts (a key of
    bench.resources.extraction.RUNTIMES; "auto": onnxruntime where it pays and checks, else torch)."""

    def __init__(self, root: str | os.PathLike, dtype: str = "fp16", *, progress,
                 chunk_frames: int = CHUNK_FRAMES,
                 chunk_done: Callable[[int, int], None] | None = None, runtime: str = "auto"):
        if dtype not in fs.DTYPES:
            raise ValueError(f"feature dtype {dtype!r} not in {tuple(fs.DTYPES)}")
        if runtime not in extraction.RUNTIMES:
            raise ValueError(f"extraction runtime {runtime!r} not in {extraction.RUNTIMES}")
        self.root, self.dtype, self.progress = Path(root), dtype, progress
        self.chunk_frames, self.chunk_done, self.runtime = chunk_frames, chunk_done, runtime
        self._open: dict[str, fs.StoredFeatures] = {}  # key without grid -> open file
        self._runs: dict[Encoder, extraction.OnnxExtractor | None] = {}  # one export an encoder
        self._tags: dict[str, str] = {}  # key without grid -> the runtime that extracted it

    def layout(self, encoder: Encoder, suite: FeatureSource, tag: str | None = None) -> fs.Layout:
        """What the file of (encoder, suite) holds; probes the encoder once on frame 0. `tag`:
        the runtime's (default: the one planned for the encoder, decided without an export)."""
        tag = extraction.planned_tag(encoder, self.runtime) if tag is None else tag
        n_frames = int(suite.state.shape[0])
        if n_frames == 0:
            raise ValueError(f"suite {suite.name!r} has no frames to encode")
        probe = encode_grid(encoder, {c: suite.images(torch.tensor([0]))[c]
                                      for c in suite.camera_keys[:1]})
        grid = next(iter(probe.values()))
        _, channels, h, w = grid.shape
        nhwc = not grid.is_contiguous() and grid.is_contiguous(memory_format=torch.channels_last)
        nhwc = nhwc and tag == "torch"  # onnxruntime returns contiguous NCHW arrays
        return fs.Layout(feature_key(encoder, suite, (h, w), self.dtype, tag),
                         tuple(suite.camera_keys), n_frames, (h, w), channels, self.dtype,
                         "nhwc" if nhwc else "nchw")

    def path(self, layout: fs.Layout) -> Path:
        return self.root / f"{layout.key}.feat"

    def stored(self, encoder: Encoder, suite: FeatureSource) -> fs.StoredFeatures:
        """The open file of (encoder, suite), built first if no completed one exists."""
        memo = feature_key(encoder, suite, None, self.dtype)
        if memo not in self._open:
            tag, run = extraction.planned_tag(encoder, self.runtime), None
            layout = self.layout(encoder, suite, tag)
            if not self.path(layout).exists() and tag != "torch":
                run = self._run(encoder, suite)  # exported and checked only to build
                if run is None:  # it failed: torch extracts, keyed as torch's
                    tag = "torch"
                    layout = self.layout(encoder, suite, tag)
            self._tags[memo] = tag
            path = self.path(layout)
            if path.exists():
                self._open[memo] = self._reopen(path, layout)
            else:
                self._open[memo] = self._build(path, layout, encoder, suite, run)
        return self._open[memo]

    def _run(self, encoder: Encoder, suite: FeatureSource) -> extraction.OnnxExtractor | None:
        """The encoder's onnxruntime extractor (exported and checked once), or None: torch."""
        if encoder not in self._runs:
            probe = suite.images(torch.tensor([0]))
            self._runs[encoder] = extraction.extractor(
                encoder, self.runtime, {c: probe[c] for c in suite.camera_keys[:1]},
                lambda images: encode_grid(encoder, images),
                say=lambda s: say(self.progress, f"features {encoder.spec.name}: {s}"))
        return self._runs[encoder]

    def pooled_features(self, encoder: Encoder, suite: FeatureSource,
                        target_grid: tuple[int, int],
                        transform: FeatureTransform | None = None) -> dict[str, PooledView]:
        """{camera: PooledView} of (encoder, suite) at `target_grid`; nothing is read yet."""
        stored = self.stored(encoder, suite)
        runtime = self._tags[feature_key(encoder, suite, None, self.dtype)]
        return {c: PooledView(stored, c, target_grid, transform, runtime)
                for c in suite.camera_keys}

    def _reopen(self, path: Path, layout: fs.Layout) -> fs.StoredFeatures:
        try:
            return fs.StoredFeatures.open(path, expect=layout)
        except fs.StoreInvalid as e:
            raise fs.StoreInvalid(f"{e}; delete {path} to have it rebuilt") from None

    def _build(self, path: Path, layout: fs.Layout, encoder: Encoder, suite: FeatureSource,
               run: extraction.OnnxExtractor | None = None) -> fs.StoredFeatures:
        label = f"features {encoder.spec.name} / {suite.name} at {layout.grid[0]}x{layout.grid[1]}"
        say(self.progress, f"{label}: encoding {layout.frames} frames x {len(layout.cameras)} "
                           f"cameras into {path.name}")
        bar = Progress(label, layout.frames, self.progress)

        def compute(start: int, stop: int) -> dict[str, Tensor]:
            images = suite.images(torch.arange(start, stop))
            cameras = {c: images[c] for c in layout.cameras}
            grids = run(cameras) if run is not None else encode_grid(encoder, cameras)
            # (B, C, h, w) -> (B, h*w, C): the tokens pool_grid would give at the same grid
            return {c: g.flatten(2).transpose(1, 2).cpu() for c, g in grids.items()}

        def done(frames: int, total: int) -> None:
            bar.update(frames, "frames")
            if self.chunk_done is not None:
                self.chunk_done(frames, total)

        return fs.build(path, layout, compute, self.chunk_frames,
                        say=lambda s: say(self.progress, f"{label}: {s}"), chunk_done=done)

    def close(self) -> None:
        for stored in self._open.values():
            stored.close()
        self._open.clear()
        self._tags.clear()
