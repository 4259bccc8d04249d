"""What an encoder costs, from the module actually built: its parameters, and its FLOPs on one
image at the size it is fed. The screen's naive baselines (bench.screen.proxies) rank by these.

FLOPs are torch.utils.flop_counter's count (2 per multiply-add; matmuls, convolutions and
attention, not element-wise ops or resizing), so a known-answer encoder that only averages and
reshapes pixels counts 0, as it should beside a network.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.utils.flop_counter import FlopCounterMode

from encoders.base import Encoder


@dataclass(frozen=True)
class EncoderCost:
    """params: every parameter of the frozen encoder (a count); flops: one forward of a
    (1, 3, S, S) image, S = input_size (pixels), the size the encoder resizes its input to."""

    params: int
    flops: int
    input_size: int


def encoder_cost(encoder: Encoder) -> EncoderCost:
    """The cost of `encoder` as built (its device and dtype kept): one forward under torch's
    FLOP counter, on a blank image (the count depends on shapes only)."""
    size = int(getattr(encoder, "input_size", None) or encoder.spec.input_size)
    first = next(encoder.parameters(), None)
    device = first.device if first is not None else torch.device("cpu")
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        encoder(torch.zeros(1, 3, size, size, device=device))
    return EncoderCost(params=sum(p.numel() for p in encoder.parameters()),
                       flops=int(counter.get_total_flops()), input_size=size)
