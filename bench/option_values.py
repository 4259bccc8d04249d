"""One option's value, checked on its own (bench.options puts them together): an empty value or
a list with no item in it is refused, never read as "not given". A script whose variable is
unset types `--encoders ''`; were that the default grid, it would launch a whole study."""

from __future__ import annotations

from pathlib import Path

import pytest

# Options whose value is one word or path: given empty, the run would quietly use the default.
# (--report is checked by report_file, the comma lists by listed.)
ONE_VALUE = ("--profile", "--grid", "--results-dir", "--camera-map", "--screen-keep",
             "--screen-by", "--screen-calibration", "--slurm-partition", "--save-baseline",
             "--baseline-dir", "--compare", "--degrade-encoder")
REPEATED = ("--policy", "--dataset", "--compare-fail")  # action="append": each value checked

# An example of each comma list, for the fix the message gives.
LIST_EXAMPLES = {"--backbones": "smolvla,pi05", "--encoders": "dinov2_s,siglip",
                 "--suites": "spatial,object", "--seeds": "0,1,2", "--controls": "native or none",
                 "--sim-tasks": "0,1,2"}


def refuse_empty(config: pytest.Config) -> None:
    """A UsageError for the first option given with an empty (or blank) value."""
    for option in ONE_VALUE + tuple(LIST_EXAMPLES) + ("--report",):
        _check_not_blank(option, config.getoption(option))
    for option in REPEATED:
        for value in config.getoption(option) or ():
            _check_not_blank(option, value)


def _check_not_blank(option: str, value) -> None:
    if isinstance(value, str) and not value.strip():
        example = LIST_EXAMPLES.get(option)
        give = f"give a value (e.g. {option} {example})" if example else "give a value"
        raise pytest.UsageError(f"{option} {value!r}: empty (an unset variable?); {give}, or "
                                f"leave {option} out for the default")


def listed(option: str, value: str | None) -> tuple[str, ...] | None:
    """A comma list's items (None: not given). One with no item in it, `--encoders ,`, is a
    ValueError naming the option: the default grid is never what an empty list means."""
    if value is None:
        return None
    items = tuple(v.strip() for v in value.split(",") if v.strip())
    if not items:
        raise ValueError(f"{option} {value!r}: no item in the list; give a comma list "
                         f"(e.g. {option} {LIST_EXAMPLES[option]}), or leave {option} out for "
                         "the default")
    return items


def seeds(values: tuple[str, ...] | None) -> tuple[int, ...] | None:
    if not values:
        return None
    bad = [v for v in values if not v.isdigit()]
    if bad:
        raise ValueError(f"--seeds {','.join(values)}: {bad} not a non-negative integer; give a "
                         "comma list such as --seeds 0,1,2")
    return tuple(int(v) for v in values)


def positive(option: str, value: int | None, what: str) -> int | None:
    if value is not None and value < 1:
        raise ValueError(f"{option} {value}: give a positive number of {what} (at least 1)")
    return value


def report_file(report: str | None) -> Path | None:
    """--report as a file path (None: not given). A folder is refused at start-up: the report
    would be lost after every cell was measured (writing REPORT.md onto a folder fails)."""
    if report is None:
        return None
    path = Path(report)
    if path.is_dir() or report.endswith(("/", "\\")):
        raise pytest.UsageError(f"--report {report}: a folder; --report names the report's file "
                                f"(its plots, CSV and JSON go beside it), e.g. --report "
                                f"{path / 'REPORT.md'}")
    return path
