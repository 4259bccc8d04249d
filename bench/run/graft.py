"""The freeze checks of a cell. The fixed wrapper itself (pool_grid, Projector, GraftFeed) lives
in the LeRobot plugin's distribution (graftcore.graft), so that an export stands alone; it is imported
here for the harness's modules, not copied.
"""

from __future__ import annotations

from torch import nn

from graftcore.graft import GraftFeed, Projector  # noqa: F401  (the harness's import point)


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
