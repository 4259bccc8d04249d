"""Small formatting helpers for REPORT.md: numbers with their uncertainty, GitHub tables."""

from __future__ import annotations

import math
from typing import Any, Sequence

from tabulate import tabulate


def is_num(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def num(x: Any, digits: int = 4) -> str:
    """A number to `digits` significant digits; 'n/a' for None/NaN."""
    return f"{x:.{digits}g}" if is_num(x) else "n/a"


def pct(x: Any) -> str:
    """A relative delta as a signed percentage: 0.5 -> '+50.0%'."""
    return f"{100 * x:+.1f}%" if is_num(x) else "n/a"


def interval(pair: Sequence[float] | None, digits: int = 4) -> str:
    if not pair or not all(is_num(v) for v in pair):
        return "n/a"
    return f"[{num(pair[0], digits)}, {num(pair[1], digits)}]"


def half_width(pair: Sequence[float] | None) -> str:
    """'±' column: half the interval width (intervals may be asymmetric; see the CI column)."""
    if not pair or not all(is_num(v) for v in pair):
        return "n/a"
    return num((pair[1] - pair[0]) / 2, 2)


def yes_no(flag: bool | None) -> str:
    return {True: "yes", False: "no", None: "n/a"}[flag]


def _cell(value: Any) -> str:
    text = str(value) if value is not None else ""
    return text.replace("\n", " ").replace("|", "\\|")


def table(rows: Sequence[Sequence[Any]], headers: Sequence[str]) -> str:
    """A GitHub-markdown table; cells are strings (pipes escaped, newlines flattened)."""
    if not rows:
        return "_(no rows)_"
    clean = [[_cell(v) for v in row] for row in rows]
    return tabulate(clean, headers=[_cell(h) for h in headers], tablefmt="github",
                    disable_numparse=True)


def bullets(lines: Sequence[str]) -> str:
    return "\n".join(f"- {line}" for line in lines)


def cells_by(groups: dict[str, list[str]], shown: int = 3) -> str:
    """{key: cell ids} -> 'key: a, b, c ... (n cell(s)); key2: ...', the keys sorted: which cells
    a caveat's groups (releases, machines) hold."""
    return "; ".join(f"{key}: {', '.join(sorted(ids)[:shown])}{' ...' if len(ids) > shown else ''} "
                     f"({len(ids)} cell(s))" for key, ids in sorted(groups.items()))
