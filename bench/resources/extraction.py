"""The runtime a feature store extracts with: torch eager (the encoder's own forward) or the same
timm model exported to ONNX and run by onnxruntime (~3x fewer ms an image for
EfficientNet-Lite0 at 224 px on one CPU thread, docs/PERFORMANCE.md).

`extractor(encoder, runtime, probe)` returns None for torch (features.encode_grid, today's
numbers bit for bit) or an `OnnxExtractor`. onnxruntime's kernels sum in other orders than
torch's, so its features differ from torch's in the last float32 bits: its `tag` goes into the
store's key (features.feature_key), so a store built by one runtime is never read as the other's.

"auto" picks onnxruntime only where it pays and is safe, else torch, with the reason said:
- a timm encoder (graftcore's TimmEncoder: the registry's, the real Lite wheels', "timm:<model>");
  a user's module (encoders.user_encoders) stays on torch, its forward is its own business;
- on the CPU, onnxruntime importable;
- a convolutional encoder (spec layout "map"): a ViT's time is in matrix products, as quick in
  torch (ViT-S/14 at 224 px, one thread: eager 440 ms an image, onnxruntime 451), so a ViT keeps
  torch's bits and skips the export;
- an input of at least ORT_MIN_INPUT px: the tiny profile's 56-64 px encoders extract in
  milliseconds, where an export's seconds would not pay, and the tiny worlds' numbers stay torch's;
- the export runs and its grid on the probe frame matches torch's within CHECK_TOLERANCE.
"onnxruntime" asks for it whatever the input size; it still falls back on the other conditions.
"""

from __future__ import annotations

import io
import math
import warnings
from typing import Callable

import torch
from torch import Tensor, nn

RUNTIMES = ("auto", "torch", "onnxruntime")
ORT_MIN_INPUT = 160  # px; below it an export (~1-5 s for a small model) outweighs extraction
OPSET = 17
# Relative to the grid's largest magnitude: float32 reordering gives ~1e-7, a wrong export
# (a BatchNorm traced in training mode, a padding baked for another size) gives ~1.
CHECK_TOLERANCE = 1e-4


class _Grid(nn.Module):
    """What a TimmEncoder computes after `normalised`: normalised pixels -> (B, C, h, w). The
    batch size is never read, so the exported graph keeps it dynamic."""

    def __init__(self, encoder: nn.Module) -> None:
        super().__init__()
        self.model = encoder.model
        self.layout, self.prefix = encoder.spec.layout, encoder.spec.num_prefix_tokens
        self.nhwc = getattr(encoder, "output_fmt", "NCHW") == "NHWC"

    def forward(self, x: Tensor) -> Tensor:
        feats = self.model.forward_features(x)
        if self.layout == "tokens":
            patches = feats[:, self.prefix:]
            # A traced size is a tensor: int() bakes it, right as the input size is fixed.
            side = math.isqrt(int(patches.shape[1]))
            return patches.transpose(1, 2).unflatten(2, (side, side))
        return feats.permute(0, 3, 1, 2) if self.nhwc else feats


class OnnxExtractor:
    """{camera: (B, 3, H, W) in [0,1]} -> {camera: (B, C, h, w) float32 on the CPU}: the
    encoder's resize and normalisation in torch (as today), its model in onnxruntime."""

    def __init__(self, encoder: nn.Module, session, tag: str) -> None:
        self.encoder, self.session, self.tag = encoder, session, tag

    def __call__(self, images_by_camera: dict[str, Tensor]) -> dict[str, Tensor]:
        out = {}
        with torch.inference_mode():
            for camera, images in images_by_camera.items():
                x = self.encoder.normalised(images.to(torch.float32)).contiguous().numpy()
                out[camera] = torch.from_numpy(self.session.run(None, {"pixels": x})[0])
        return out


def onnx_tag() -> str:
    import onnxruntime

    return f"onnxruntime=={onnxruntime.__version__}/opset{OPSET}"


def _session(encoder: nn.Module, threads: int):
    """An onnxruntime session of the encoder's model (export: batch 2, dynamic batch axis)."""
    import onnxruntime

    module = _Grid(encoder).eval()  # export restores this module's mode: eval, never train
    example = encoder.normalised(torch.zeros(2, 3, encoder.input_size, encoder.input_size))
    buf = io.BytesIO()
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation and trace notes
        torch.onnx.export(module, (example,), buf, dynamo=False, opset_version=OPSET,
                          input_names=["pixels"], output_names=["feature_map"],
                          dynamic_axes={"pixels": {0: "batch"}, "feature_map": {0: "batch"}})
    options = onnxruntime.SessionOptions()
    # The session's threads are torch's: one knob (--threads) for every runtime, and a fixed
    # count keeps its sums' order, hence its bits, the same run to run.
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    options.log_severity_level = 3
    return onnxruntime.InferenceSession(buf.getvalue(), options,
                                        providers=["CPUExecutionProvider"])


def _why_not(encoder: nn.Module, runtime: str) -> str | None:
    """Why `encoder` stays on torch under `runtime`, or None when onnxruntime may be tried."""
    from graftcore.encoder import TimmEncoder

    if runtime == "torch":
        return ""
    if type(encoder) is not TimmEncoder:
        return "not a timm encoder"
    if any(t.device.type != "cpu" for t in (*encoder.parameters(), *encoder.buffers())):
        return "the encoder is not on the CPU"
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        return "onnxruntime is not installed (pip install onnxruntime onnx)"
    if runtime == "auto" and (encoder.input_size < ORT_MIN_INPUT
                              or encoder.spec.layout != "map"):
        return ""  # the tiny profile's inputs, or a ViT: torch is as quick, say nothing
    return None


def extractor(encoder: nn.Module, runtime: str, probe: dict[str, Tensor],
              torch_grid: Callable[[dict[str, Tensor]], dict[str, Tensor]],
              say: Callable[[str], None] = lambda s: None) -> OnnxExtractor | None:
    """The onnxruntime extractor of `encoder`, checked on `probe` against `torch_grid` (torch's
    encode_grid), or None: extract with torch. Falls back with `say(reason)` (never raises)."""
    if runtime not in RUNTIMES:
        raise ValueError(f"extraction runtime {runtime!r} not in {RUNTIMES}")
    reason = _why_not(encoder, runtime)
    if reason is None:
        try:
            candidate = OnnxExtractor(encoder, _session(encoder, torch.get_num_threads()),
                                      onnx_tag())
            got, want = candidate(probe), torch_grid(probe)
            for camera, grid in want.items():
                scale = float(grid.abs().max()) + 1.0
                if got[camera].shape != grid.shape or \
                        float((got[camera] - grid).abs().max()) > CHECK_TOLERANCE * scale:
                    raise ValueError("its grid differs from torch's on the probe frame")
            return candidate
        except Exception as err:  # an export timm or torch.onnx cannot do: torch still can
            first = (str(err).splitlines() or [""])[0][:160]
            reason = f"onnx export failed ({type(err).__name__}: {first})"
    if reason:
        say(f"extracting with torch: {reason}")
    return None


def planned_tag(encoder: nn.Module, runtime: str) -> str:
    """The runtime tag a store plans for `encoder` before any export: "torch", or onnx_tag()
    when onnxruntime will be tried (a failed export then falls back, keyed "torch")."""
    return onnx_tag() if _why_not(encoder, runtime) is None else "torch"
