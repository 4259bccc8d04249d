"""What every REPORT.md section reads: the stored records and the analyses computed once."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from bench.analysis.rankings import PRIMARY, Ranking
from bench.analysis.controls import ControlDelta, VisionCheck, WrapperNeutrality
from bench.analysis.rollouts import ClosedLoop
from bench.analysis.transfer import Transfer
from bench.results.store import Results
from bench.report.format import pct


@dataclass
class ReportContext:
    """Everything the sections need, computed once from the stored records."""

    results: Results
    out_path: Path
    rankings: list[Ranking]
    transfers: list[Transfer]
    support: dict
    wrapper: dict[tuple[str, str], WrapperNeutrality]
    controls: list[ControlDelta]
    plots: list[tuple[str, Path]] = field(default_factory=list)
    n_resamples: int = 0
    closed_loop: list[ClosedLoop] = field(default_factory=list)
    vision: list[VisionCheck] = field(default_factory=list)
    screen_agreements: list = field(default_factory=list)  # bench.analysis.tiers.TierAgreement
    # {results dir: bench.report.screen.Calibration} of the studies named by --screen-calibration
    screen_calibrations: dict = field(default_factory=dict)
    # The stored screens' ScreenScores, each with every naive baseline (bench.report.naive), and
    # the ids of those whose were counted when the report was built.
    screens: list = field(default_factory=list)
    naive_filled: list[str] = field(default_factory=list)
    # The labels of the candidate items (bench.analysis.candidates): encoders and "native".
    candidates: frozenset[str] = frozenset()
    # The verdict within the closed loop's working group (bench.analysis.working_group).
    working_groups: list = field(default_factory=list)
    # Family or scale over the tiny ladder (bench.analysis.family_scale): a SuiteVerdict per suite
    # with a comparison, and the small-model rung's TierAgreements (both item sets).
    family_scale: list = field(default_factory=list)
    small_model: list = field(default_factory=list)

    @property
    def records(self) -> list[dict]:
        return self.results.records

    def vision_of(self, backbone: str, suite: str) -> VisionCheck | None:
        return next((v for v in self.vision if (v.backbone, v.suite) == (backbone, suite)), None)

    def wrapper_text(self, backbone: str, suite: str) -> str:
        wn = self.wrapper.get((backbone, suite))
        if wn is None or not wn.mean:
            return "not measured (no native + native_wrapped pair)"
        cells = list(wn.per_seed)
        if all(isinstance(c, int) for c in cells):
            return f"{pct(wn.mean[PRIMARY])} (mean over seeds {sorted(cells)})"
        return f"{pct(wn.mean[PRIMARY])} (mean over {len(cells)} release x seed cells)"
