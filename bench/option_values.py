"""One option's value, checked on its own (bench.options puts them together): an empty value or
a list with no item in it is refused, never read as "not given". A script whose variable is
unset types `--encoders ''`; were that the default grid, it would launch a whole study."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NoReturn

import pytest

# Bad input exits with this code from every entry point: `pytest bench` (pytest's usage error),
# `python -m bench.report`, `bench.export`, `bench.offline_hub`, `bench.sim.demos`.
USAGE_ERROR = int(pytest.ExitCode.USAGE_ERROR)  # 4


def refuse(prog: str, message: str) -> NoReturn:
    """A `python -m` entry point's bad input: one line on stderr (what, the value, the fix),
    exit USAGE_ERROR, nothing written."""
    print(f"{prog}: {message}", file=sys.stderr)
    raise SystemExit(USAGE_ERROR)


def whole_at_least(least: int, example: str):
    """An argparse `type` for a `python -m` entry point: a whole number >= `least`, else one
    line with the fix (`--resamples 0: give a whole number >= 2, e.g. 2000`)."""
    def parse(value: str) -> int:
        try:
            n = int(value)
        except ValueError:
            n = None
        if n is None or n < least:
            raise argparse.ArgumentTypeError(f"{value}: give a whole number >= {least}, e.g. "
                                             f"{example}")
        return n

    return parse


class CommandParser(argparse.ArgumentParser):
    """argparse for the `python -m` entry points: an argument error is one line naming the
    argument and the fix (argparse's own usage block only under --help), exit USAGE_ERROR (argparse
    exits 2, pytest bench 4: one code for bad input everywhere)."""

    def error(self, message: str) -> NoReturn:
        refuse(self.prog, f"{message}; see {self.prog} --help")

# Options whose value is one word or path: given empty, the run would quietly use the default.
# (--report is checked by report_file, the comma lists by listed.)
ONE_VALUE = ("--profile", "--grid", "--results-dir", "--camera-map", "--screen-keep",
             "--screen-by", "--screen-calibration", "--slurm-partition", "--save-baseline",
             "--baseline-dir", "--compare", "--degrade-encoder")
REPEATED = ("--policy", "--dataset", "--compare-fail")  # action="append": each value checked

# An example of each comma list, for the fix the message gives.
LIST_EXAMPLES = {"--backbones": "smolvla,pi05", "--encoders": "dinov2_s,siglip",
                 "--suites": "spatial,object", "--seeds": "0,1,2", "--controls": "native or none",
                 "--sim-tasks": "0,1,2", "--robustness": "brightness,blur:1,3 (or all)"}


def refuse_empty(config: pytest.Config) -> None:
    """A UsageError for the first option given with an empty (or blank) value."""
    for option in ONE_VALUE + tuple(LIST_EXAMPLES) + ("--report",):
        _check_not_blank(option, config.getoption(option))
    for option in REPEATED:
        for value in config.getoption(option) or ():
            _check_not_blank(option, value)
    try:  # the robustness list is read by bench.robust.cases, where `,,,` meant "off"
        listed("--robustness", config.getoption("--robustness"))
    except ValueError as e:
        raise pytest.UsageError(str(e)) from None


def _check_not_blank(option: str, value) -> None:
    if isinstance(value, str) and not value.strip():
        example = LIST_EXAMPLES.get(option)
        give = f"give a value (e.g. {option} {example})" if example else "give a value"
        raise pytest.UsageError(f"{option} {value!r}: empty (an unset variable?); {give}, or "
                                f"leave {option} out for the default")


def wrong_case(option: str, value: str, keywords: tuple[str, ...]) -> str | None:
    """The refusal of a keyword written in another case (`--screen-keep ALL`), else None. Every
    keyword and choice is lower case and exact, as --executor's and --features' are: one rule
    for every option, never read one way here and refused there."""
    text = str(value).strip()
    for keyword in keywords:
        if text != keyword and text.lower() == keyword:
            return f"{option} {value}: keywords are lower case; give {option} {keyword}"
    return None


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


def control_list(given: str | None) -> tuple[str, ...] | None:
    """--controls as kinds (None: not given; `none`: ()), each known, in lower case; a
    ValueError naming the nearest kind otherwise."""
    import difflib

    from bench.grid.kinds import control_kinds

    controls = listed("--controls", given)
    for c in controls or ():
        if problem := wrong_case("--controls", c, ("none",) + control_kinds()):
            raise ValueError(problem)
    if controls == ("none",):
        return ()
    bad = [c for c in controls or () if c not in control_kinds()]
    if bad:
        close = difflib.get_close_matches(bad[0], control_kinds(), n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise ValueError(f"--controls {given}: unknown control kind(s) {bad}{hint}; valid: "
                         f"{', '.join(control_kinds())} (or none)")
    return controls


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


def number(option: str, value, kind: type = int, example: str = "10"):
    """A number option's value (None: not given). Declared without argparse's `type=`, so a typo
    is this one line with the fix, not argparse's usage block: `--steps 1e3` -> give 1000."""
    if value is None or isinstance(value, kind) and not isinstance(value, bool):
        return value
    text = str(value).strip()
    try:
        return kind(text)
    except ValueError:
        pass
    what = "a whole number" if kind is int else "a number"
    try:
        as_float = float(text)
        if kind is int and as_float.is_integer():
            example = str(int(as_float))  # 1e3 or 100.0: the number meant, written whole
    except ValueError:
        pass
    raise pytest.UsageError(f"{option} {value}: not {what}; give e.g. {option} {example}")


# Number options, declared without argparse's `type=` (a typo there is argparse's usage block):
# (kind, an example for the fix). `typed_options` converts them once, at start-up.
NUMBERS = {"--steps": (int, "1000"), "--rollouts": (int, "10"), "--rollout-batch": (int, "5"),
           "--rollout-workers": (int, "2"),
           "--sim-demos": (int, "3"), "--sim-demo-noise": (float, "0.1"),
           "--sim-demo-speed": (float, "0.5"), "--slurm-time": (int, "240"),
           "--slurm-gpus-per-task": (int, "1"), "--slurm-array-parallelism": (int, "64"),
           "--pack-grafts": (int, "4")}
# Options with a few values, declared without argparse's `choices=` for the same reason.
CHOICES = {"--features": ("cache", "loop"), "--feature-dtype": ("fp16", "bf16", "float32"),
           "--rollout-envs": ("sync", "async"), "--executor": ("local", "slurm", "submitit-local")}


def typed_options(config: pytest.Config) -> None:
    """Every NUMBERS option converted in place (config.option: what the rest reads) and every
    CHOICES option checked: a bad value is one UsageError line with the fix."""
    for option, (kind, example) in NUMBERS.items():
        dest = option.lstrip("-").replace("-", "_")
        setattr(config.option, dest, number(option, config.getoption(option), kind, example))
    for option, choices in CHOICES.items():
        choice(option, config.getoption(option), choices)


def choice(option: str, value: str, choices: tuple[str, ...]) -> str:
    """A value from `choices`, else one line naming them (not argparse's usage block)."""
    if value in choices:
        return value
    import difflib

    close = difflib.get_close_matches(str(value), choices, n=1, cutoff=0.5)
    give = close[0] if close else choices[0]
    raise pytest.UsageError(f"{option} {value}: not one of {', '.join(choices)}; give e.g. "
                            f"{option} {give}")


def pack_grafts(given: int | None, grid_file, executor: str) -> int:
    """Graft cells trained per backbone pass (bench.cell.pack_run): --pack-grafts, else the grid
    file's `pack_grafts` (checked when the file was read), else 1. A run setting: the protocol
    and every record's identity stay as they are. K > 1 needs cells measured in this process."""
    where = f"--pack-grafts {given}"
    if given is None and grid_file is not None:
        import tomllib

        given = tomllib.loads(grid_file.text).get("pack_grafts")
        where = f"{grid_file.path}: pack_grafts = {given}"
    if given is None:
        return 1
    if given < 1:
        raise pytest.UsageError(f"{where}: give a whole number of grafts per backbone pass >= 1, "
                                "e.g. --pack-grafts 4 (1: one at a time, the default)")
    if given > 1 and executor != "local":
        raise pytest.UsageError(f"{where} with --executor {executor}: each array task measures "
                                "one cell in its own process, so no pack can form; fix: "
                                "--executor local, or drop the packing")
    return given


def protocol_value(option: str, field: str, value):
    """A command-line value of a Protocol field, in the one range table (bench.grid.protocol:
    a grid file's `steps` and `[protocol]` read the same table, with the same message)."""
    from bench.grid.protocol import range_error

    problem = None if value is None else range_error(field, value, option)
    if problem:
        raise ValueError(problem)
    return value


def report_folder_refusal(option: str, out: str | Path) -> str | None:
    """Why `out` names a folder, not the report's file (None: it does not): an existing folder,
    or a path given with a trailing separator (pass the text as typed: a Path drops it)."""
    if Path(out).is_dir() or str(out).endswith(("/", "\\")):
        return (f"{option} {out}: a folder; {option} names the report's file (its plots, CSV and "
                f"JSON go beside it), e.g. {option} {Path(out) / 'REPORT.md'}")
    return None


def report_file(report: str | None) -> Path | None:
    """--report as a file path (None: not given). A folder is refused at start-up: the report
    would be lost after every cell was measured (writing REPORT.md onto a folder fails)."""
    if report is None:
        return None
    if problem := report_folder_refusal("--report", report):
        raise pytest.UsageError(problem)
    return Path(report)
