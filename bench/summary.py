"""What a run did, for the end of the terminal output: cells measured / resumed / failed (each
failure with its one-line reason), where the records and the report went, the headline answer."""

from __future__ import annotations

from pathlib import Path

from bench.results.store import CELLS
from bench.cell.outcome import Outcome, tally



def cell_id_of(nodeid: str) -> str | None:
    """`bench/test_grid.py::test_graft[smolvla-spatial-dinov2_s-seed0]` -> the cell id."""
    if "[" not in nodeid:
        return None
    return nodeid.split("@")[0].rsplit("[", 1)[-1].rstrip("]")


def failure_line(results_dir: Path, cell_id: str, longrepr: str) -> str:
    """The failure record's error when the cell wrote one, else the report's last line."""
    from bench.results.store import load_failure

    failure = load_failure(results_dir, cell_id)
    if failure is not None:
        return " ".join(failure.error.split())[:300]
    lines = [ln.strip() for ln in longrepr.splitlines() if ln.strip()]
    return (lines[-1] if lines else "failed")[:300]


def headline(report: Path) -> str | None:
    """The report's first paragraph after its title (the answer, in one line)."""
    if not report.is_file():
        return None
    for line in report.read_text().splitlines()[1:]:
        if line.strip() and not line.startswith("#"):
            return " ".join(line.split())[:400]
    return None


def summary_lines(profile: str, protocol_hash: str, outcomes: dict[str, Outcome], selected: int,
                  results_dir: Path, report: Path, written: bool,
                  report_error: str | None = None) -> list[str]:
    measured, resumed, failed = tally(outcomes)
    lines = [f"profile {profile}, protocol {protocol_hash}",
             f"cells selected {selected}: measured {measured}, resumed from store {resumed}, "
             f"failed {len(failed)}",
             f"records: {results_dir / CELLS}"]
    if written:
        lines.append(f"report: {report}")
    elif report_error is not None:
        lines.append(f"report: NOT WRITTEN to {report} ({report_error})")
    elif report.exists():
        lines.append(f"report: {report} left as it was (this run finished no new cell)")
    else:
        lines.append("report: not written (no cell finished)")
    answer = headline(report) if report.is_file() else None
    if answer:
        lines.append(f"answer: {answer}")
    lines += [f"FAILED {cell}: {reason}" for cell, reason in sorted(failed.items())]
    return lines


def screen_summary_lines(outcomes: dict[str, Outcome], dropped: dict[str, str]) -> list[str]:
    """--screen: screens measured / resumed / failed, and each cell the screen dropped, why."""
    measured, resumed, failed = tally(outcomes)
    lines = [f"screens {len(outcomes)}: measured {measured}, resumed from store {resumed}, "
             f"failed {len(failed)}; cells dropped by the screen {len(dropped)}"]
    lines += [f"SCREEN FAILED {sid}: {why}" for sid, why in sorted(failed.items())]
    lines += [f"dropped {cell}: {why}" for cell, why in sorted(dropped.items())]
    return lines
