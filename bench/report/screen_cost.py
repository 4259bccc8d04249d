"""REPORT.md's "Cost per encoder" table (the screen section): what each tier of the ladder cost
each screened encoder, so that "the screen costs at most 5% of a graft cell for every encoder"
reads off one column.

Per backbone x suite, one row per screened encoder: the screen's own solve (ScreenScores.seconds,
extraction not counted), the feature extraction (its stored file's build time, whichever tier ran
it: a screen that found the graft's features stored is not free), each short graft's and the
graft's wall seconds per cell (RunInfo.total_s, mean over seeds) and screen / graft. Then one
summary row: the mean of each column over the encoders, and the worst screen / graft with its
encoder. Then, where a grid holds several sizes of a family (backbones.tiny_sizes), the cost of
"screening on the small model of the family": its graft seconds per cell against the family's
largest size's. Pure: stored screens and records in, markdown out."""

from __future__ import annotations

import statistics
from dataclasses import dataclass
from typing import Sequence

from bench.analysis.family_scale import screening_rungs
from bench.analysis.tiers import short_tier
from bench.grid.kinds import GRAFT, SHORT_GRAFT, get_kind
from bench.report.format import num, table


@dataclass(frozen=True)
class EncoderCost:
    """One screened encoder's seconds on one backbone x suite (None: no record of that tier)."""

    encoder: str
    screen: float
    extraction: float
    shorts: tuple[float | None, ...]  # per short-graft variant, in the kind's variant order
    graft: float | None

    @property
    def ratio(self) -> float | None:
        """Screen / graft cell, or None without a graft record."""
        return self.screen / self.graft if self.graft else None


def encoder_costs(stored: Sequence, records: Sequence, backbone: str,
                  suite: str) -> list[EncoderCost]:
    """EncoderCost of every screen stored on backbone x suite, by encoder name."""
    variants = get_kind(SHORT_GRAFT).variants
    mine = sorted((r for r in stored if (r.scores.backbone, r.scores.suite) == (backbone, suite)),
                  key=lambda r: r.scores.encoder)
    return [EncoderCost(r.scores.encoder, r.scores.seconds, extraction_seconds(r),
                        tuple(cell_seconds(records, backbone, suite, SHORT_GRAFT, v,
                                           r.scores.encoder) for v in variants),
                        cell_seconds(records, backbone, suite, GRAFT, None, r.scores.encoder))
            for r in mine]


def extraction_seconds(screen) -> float:
    """A screen's feature extraction seconds: its file's, else (older records) its own."""
    return (screen.extraction_seconds if screen.extraction_seconds is not None
            else screen.feature_seconds)


def cell_seconds(records: Sequence, backbone: str, suite: str, kind: str,
                 variant: str | None, encoder: str | None = None,
                 average=statistics.fmean) -> float | None:
    """The `average` (mean unless given) measured wall seconds per cell of the kind x variant's
    records on backbone x suite (of one `encoder`, when given); None when there is none."""
    seconds = [r.run.total_s for r in records if r.kind == kind and r.variant == variant
               and (r.backbone, r.suite) == (backbone, suite) and r.run.total_s is not None
               and (encoder is None or r.encoder == encoder)]
    return average(seconds) if seconds else None


def _mean(values) -> float | None:
    known = [v for v in values if v is not None]
    return sum(known) / len(known) if known else None


def _seconds(value: float | None, missing: str = "no record") -> str:
    return num(value, 3) if value is not None else missing


def _percent(value: float | None) -> str:
    return f"{100 * value:.1f}%" if value is not None else "n/a"


def summary_row(costs: Sequence[EncoderCost]) -> list[str]:
    """The mean of each column over the encoders (of those with a record), then the mean and the
    worst screen / graft, naming the worst encoder."""
    ratios = [(c.ratio, c.encoder) for c in costs if c.ratio is not None]
    worst = max(ratios, default=None)
    shorts = zip(*(c.shorts for c in costs))
    return ([f"**mean of {len(costs)}**", num(_mean(c.screen for c in costs), 3),
             num(_mean(c.extraction for c in costs), 3)]
            + [_seconds(_mean(s)) for s in shorts]
            + [_seconds(_mean(c.graft for c in costs), "no graft record"),
               f"{_percent(_mean(r for r, _ in ratios))}; worst "
               + (f"{_percent(worst[0])} ({worst[1]})" if worst else "n/a")])


def cost_table(stored: Sequence, records: Sequence) -> str:
    """The table of the module doc, every backbone x suite with a stored screen."""
    variants = get_kind(SHORT_GRAFT).variants
    rows = []
    for backbone, suite in sorted({(r.scores.backbone, r.scores.suite) for r in stored}):
        costs = encoder_costs(stored, records, backbone, suite)
        rows += [[backbone, suite, c.encoder, num(c.screen, 3), num(c.extraction, 3)]
                 + [_seconds(s) for s in c.shorts]
                 + [_seconds(c.graft, "no graft record"), _percent(c.ratio)] for c in costs]
        rows.append([backbone, suite] + summary_row(costs))
    return table(rows, ["backbone", "suite", "encoder", "screen s",
                        "extraction s (whichever tier ran it)"]
                 + [f"{short_tier(v)} s / cell" for v in variants]
                 + ["graft s / cell", "screen / graft"])


def small_model_cost_rows(records: Sequence) -> list[list[str]]:
    """Per screening rung: the small and the large model's graft seconds per cell (the median
    over their cells, RunInfo.total_s: the cell that first loads a release not yet trained holds
    its native training, 22 min of pi05_l's, in its build time) and their ratio, the rung's cost
    per encoder."""
    rows = []
    for small, large, suite in screening_rungs(records):
        s, big = (cell_seconds(records, b, suite, GRAFT, None, average=statistics.median)
                  for b in (small, large))
        ratio = _percent(s / big if s is not None and big else None)
        rows.append([suite, small, large, num(s, 3), num(big, 3), ratio])
    return rows


SMALL_MODEL_COST_HEADERS = ["suite", "small model", "large model", "small graft s / cell",
                            "large graft s / cell", "small / large"]
SMALL_MODEL_COST_TEXT = (
    "**Cost of screening on the small model** (per encoder: one graft cell of the small model "
    "against one of the large, the median cell of each; the native training of either, once "
    "per release, is not counted). Wall seconds as each cell ran: a record holds no load, so rungs measured in "
    "different runs, or beside other jobs, compare loosely (a study's own side-by-side step "
    "costs are the figure to read for that)")
