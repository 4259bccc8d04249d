"""What a real encoder's extraction costs beside the tiny encoders it stands with (issue 36):

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
PER_FRAME: dict[str, float] = {}


@pytest.fixture(scope="module")
def frames() -> torch.Tensor:
    return torch.rand(FRAMES, 3, 128, 128, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("name", ENCODERS)
def test_extract(benchmark, frames, name):
    from encoders import build_encoder

    encoder = build_encoder(name, "tiny")
    encoder(frames[:2])  # first call outside the timing (allocator, lazy init)
    benchmark.pedantic(encoder, args=(frames,), rounds=5, iterations=1)
    PER_FRAME[name] = benchmark.stats.stats.median / FRAMES


def test_ratios_to_the_tiny_reference(capsys):
    if REFERENCE not in PER_FRAME:
        pytest.skip("run with the extraction benchmarks (--benchmark-only runs them first)")
    with capsys.disabled():
        print(f"\nper frame (median of 5 rounds, 1 thread), ratio to {REFERENCE}:")
        for name, seconds in PER_FRAME.items():
            print(f"  {name:<22} {seconds * 1e3:8.2f} ms  x{seconds / PER_FRAME[REFERENCE]:6.1f}")
