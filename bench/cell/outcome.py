"""What became of one case of a run (a cell, a screen, a robustness case): measured here, resumed
from the store, or failed with its one line. One type for all three, so no caller compares
strings; `text` is its form in a pytest report's user property (how an xdist worker tells the
controller) and `of_text` reads it back."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

OUTCOME_PROPERTY = "graftbench"  # the pytest user property a case reports its outcome under


class Status(Enum):
    MEASURED = "measured"
    RESUMED = "resumed"
    FAILED = "failed"


@dataclass(frozen=True)
class Outcome:
    status: Status
    reason: str = ""  # a failure's one line

    @property
    def text(self) -> str:
        return self.reason if self.status is Status.FAILED else self.status.value

    @classmethod
    def of_text(cls, text: str) -> Outcome:
        """The outcome a report property carried ("measured", "resumed", else a failure line)."""
        for status in (Status.MEASURED, Status.RESUMED):
            if text == status.value:
                return cls(status)
        return failed(text)

    @property
    def failed(self) -> bool:
        return self.status is Status.FAILED


MEASURED = Outcome(Status.MEASURED)
RESUMED = Outcome(Status.RESUMED)


def failed(reason: str) -> Outcome:
    return Outcome(Status.FAILED, reason)


def tally(outcomes) -> tuple[int, int, dict]:
    """(measured, resumed, {id: failure line}) of a {id: Outcome} mapping."""
    measured = sum(1 for o in outcomes.values() if o.status is Status.MEASURED)
    resumed = sum(1 for o in outcomes.values() if o.status is Status.RESUMED)
    return measured, resumed, {k: o.reason for k, o in outcomes.items() if o.failed}
