"""The freeze checks of a cell (only the projector, plus LoRA or the encoder where the kind says,
may train), and the tuned-encoder control's private copy of its encoder. The fixed wrapper itself
(pool_grid, Projector, GraftFeed) is the LeRobot plugin's (graftcore.graft), so that an export
stands alone.
"""

from __future__ import annotations

import copy

from torch import nn


def trainable_parameters(*modules: nn.Module) -> int:
    """Number of parameters with requires_grad over the given modules (shared ones once)."""
    seen: set[int] = set()
    total = 0
    for module in modules:
        for p in module.parameters():
            if p.requires_grad and id(p) not in seen:
                seen.add(id(p))
                total += p.numel()
    return total


def assert_only_trainable(expected: int, *modules: nn.Module, what: str = "projector") -> None:
    """Freeze check of every cell: the trainable count must equal the projector's (+ LoRA)."""
    found = trainable_parameters(*modules)
    if found != expected:
        names = [
            n for m in modules for n, p in m.named_parameters() if p.requires_grad
        ][:8]
        raise AssertionError(
            f"freeze violated: {found} trainable parameters, expected {expected} ({what}); "
            f"first trainable: {names}"
        )


def tunable_copy(encoder: nn.Module, name: str) -> nn.Module:
    """A private copy of a session's frozen encoder whose weights train (the tuned-encoder
    control): the session's own stays frozen for every other cell and the feature store. Its
    normalisation statistics and dropout stay in eval mode (a frozen encoder's `train()` keeps
    them so): only the weights change, and training and evaluation run the same function."""
    tuned = copy.deepcopy(encoder)
    tuned.requires_grad_(True)
    if trainable_parameters(tuned) == 0 or not callable(getattr(tuned, "grid", None)):
        raise ValueError(f"encoder {name!r} has no weights to tune through autograd (a grid() "
                         "entry); run the tuned-encoder control for a timm-built encoder")
    return tuned
