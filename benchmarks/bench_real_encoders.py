"""What a real encoder's extraction costs beside the tiny encoders it stands with:

    .venv/bin/pytest benchmarks/bench_real_encoders.py --benchmark-only -p no:randomly

One batch of 16 frames of 128 px (the sim suites' renders), each encoder at its own input size
(the real ones at their pretrained 224 / 240 / 260 px, the tiny ones at 56-64 px), 5 rounds on one
thread. The session ends with each encoder's time per frame as a ratio to dinov2_s (tiny) from
this same run: ratios, not lone absolute times, travel between machines.
"""

from __future__ import annotations

import pytest
import torch

ENCODERS = ("dinov2_s", "pixels_p16", "effnet_lite0_random", "effnet_lite0", "effnet_lite0_s4",
            "effnet_lite1", "effnet_lite2")
REFERENCE = "dinov2_s"
FRAMES = 16


@pytest.fixture(scope="module")
def per_frame(request):
    """encoder -> seconds per frame (median round); printed as ratios when the module ends
    (a fixture's teardown, so --benchmark-only, which skips plain tests, still prints them)."""
    found: dict[str, float] = {}
    yield found
    if REFERENCE in found:
        reporter = request.config.pluginmanager.get_plugin("terminalreporter")
        reporter.write_line(f"\nper frame (median of 5 rounds, 1 thread), ratio to {REFERENCE}:")
        for name, seconds in found.items():
            reporter.write_line(f"  {name:<22} {seconds * 1e3:8.2f} ms  "
                                f"x{seconds / found[REFERENCE]:6.1f}")


@pytest.fixture(scope="module")
def frames() -> torch.Tensor:
    return torch.rand(FRAMES, 3, 128, 128, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("name", ENCODERS)
def test_extract(benchmark, frames, per_frame, name):
    from encoders import build_encoder

    encoder = build_encoder(name, "tiny")
    encoder(frames[:2])  # first call outside the timing (allocator, lazy init)
    benchmark.pedantic(encoder, args=(frames,), rounds=5, iterations=1)
    per_frame[name] = benchmark.stats.stats.median / FRAMES
