"""What a --screen run grafts on each backbone x suite: `--screen-by` and `--screen-keep` parsed,
and the best `keep` encoders by one proxy of the table (bench.screen.proxies), or by the short
graft's MSE (`--screen-by short`), beside the references. Imports nothing heavy: the options read
it at start-up."""

from __future__ import annotations

from dataclasses import dataclass

from bench.screen.proxies import DEFAULT_PROXY, proxy_names
from bench.screen.records import ScreenScores, ScreenSelection
from bench.stats import Measure, is_defined

SHORT = "short"  # --screen-by short: the short-graft tier (bench.grid.kinds SHORT_BY_VARIANT)
DEFAULT_SCREEN_BY = DEFAULT_PROXY
# Grafted whatever the screen says: the known-answer anchors (all the information in the images,
# none of it) every ranking of a --screen run is read against.
REFERENCES = ("pixels", "blind")


def screen_by_choices() -> tuple[str, ...]:
    """What --screen-by accepts: every proxy of the table, in its order, then short. Read when
    asked, not frozen at import: a proxy registered later is a choice too."""
    return proxy_names() + (SHORT,)


@dataclass(frozen=True)
class ScreenOptions:
    """A --screen run: graft the `keep` best encoders (None: all) by proxy `by`; `calibration`:
    the results dir of the calibration study whose agreement its report quotes (checked at
    start-up: bench.results.store.load_calibration)."""

    keep: int | None
    by: str = DEFAULT_SCREEN_BY
    calibration: str | None = None


@dataclass(frozen=True)
class ShortScores:
    """An encoder's short-graft score for `select_for_graft`: its normalised held-out MSE at the
    ranking fraction, mean over seeds (lower is better; the score is -MSE, higher is better)."""

    encoder: str
    mse: Measure

    def score(self, proxy: str) -> Measure:
        return -self.mse if is_defined(self.mse) else self.mse


def _shown(by: str, score: float) -> str:
    return f"MSE {-score:.4g}" if by == SHORT else f"{score:.4g}"


def parse_screen_keep(value: str) -> int | None:
    """`--screen-keep` as a count (None: "all"); ValueError with one line for anything else."""
    from bench.option_values import wrong_case

    text = str(value).strip()
    if problem := wrong_case("--screen-keep", value, ("all",)):
        raise ValueError(problem)
    if text == "all":
        return None
    try:
        keep = int(text)
    except ValueError:
        keep = 0
    if keep < 1 or str(keep) != text.lstrip("+"):
        raise ValueError(f"--screen-keep {value}: give a whole number >= 1, or all")
    return keep


def parse_screen_by(value: str) -> str:
    """`--screen-by` checked against the proxy table and short; ValueError with one line naming
    the valid ones."""
    choices = screen_by_choices()
    if value not in choices:
        raise ValueError(f"--screen-by {value}: unknown proxy; choose one of {', '.join(choices)}")
    return value


def select_for_graft(backbone: str, suite: str, screens: list[ScreenScores | ShortScores],
                     options: ScreenOptions, references: tuple[str, ...] = (),
                     failed: dict[str, str] | None = None) -> ScreenSelection:
    """What to graft on `backbone` x `suite`: the `options.keep` best non-reference screens by
    `options.by` (anything with `.encoder` and `.score(by)`: ScreenScores, or ShortScores for
    --screen-by short; higher is better; ties: the encoder name), every reference, and each dropped
    encoder with why: its rank and score, its undefined score's reason, or its screen's failure
    (`failed`: {encoder: error}). keep > screened is allowed and noted."""
    by, keep = parse_screen_by(options.by), options.keep
    candidates = [s for s in screens if s.encoder not in references]
    defined = [(s.encoder, s.score(by)) for s in candidates if is_defined(s.score(by))]
    dropped = {s.encoder: f"{by} {s.score(by)}" for s in candidates if not is_defined(s.score(by))}
    dropped |= {e: f"its screen failed: {why}" for e, why in (failed or {}).items()
                if e not in references}
    ranked = sorted(defined, key=lambda item: (-item[1], item[0]))
    count = len(ranked) if keep is None else min(keep, len(ranked))
    note = (f"--screen-keep {keep} is more than the {len(ranked)} encoder(s) with a defined "
            f"{by} score: all are grafted" if keep is not None and keep > len(ranked) else None)
    for rank, (encoder, score) in enumerate(ranked[count:], start=count + 1):
        dropped[encoder] = (f"{by} rank {rank} of {len(ranked)} ({_shown(by, score)}), below "
                            f"the top {count}")
    kept = tuple(e for e, _ in ranked[:count])
    return ScreenSelection(backbone, suite, by, keep, kept, tuple(references), dropped, note,
                           options.calibration)
