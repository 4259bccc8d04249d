"""CI regression mode in a session: `--save-baseline`, `--compare`, `--compare-fail`.

`BaselineRun` is a member of the GraftSession (bench.session), as pytest-benchmark keeps save,
compare and fail in its session object; the statistics are bench.regression.baseline's.
- cell checks (`mse:10%`, ...) run on each cell's record as its case runs, and fail THAT case
  with a one-line message;
- rank checks need every cell of a group, so they run once at session end (controller), over the
  store: flipped groups are listed in the terminal summary and REPORT.md, and the exit status
  becomes non-zero;
- the "Against baseline NAME" section is handed to the report the session builds.
"""

from __future__ import annotations

import datetime as dt
import platform
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest

from bench.regression import baseline as B
from ondisk.paths import REPO_ROOT

DEFAULT_BASELINE_DIR = REPO_ROOT / ".graftbench" / "baselines"


class BaselineMismatchWarning(pytest.PytestWarning):
    """The run and the baseline were measured under a different protocol or package versions."""


def add_baseline_options(parser: pytest.Parser) -> None:
    g = parser.getgroup("graftbench-baseline", "graftbench CI regression mode")
    g.addoption("--save-baseline", metavar="NAME",
                help="at session end, snapshot the selected cells' stored records as baseline "
                     "NAME (NAME.json in --baseline-dir)")
    g.addoption("--replace-baseline", action="store_true",
                help="let --save-baseline replace a saved baseline of that name")
    g.addoption("--baseline-dir", metavar="DIR",
                help=f"where baselines live (default {DEFAULT_BASELINE_DIR})")
    g.addoption("--compare", metavar="NAME",
                help="compare this run with baseline NAME (a name in --baseline-dir, or a .json path)")
    g.addoption("--compare-fail", metavar="SPEC", action="append", default=[],
                help="fail on regression (repeatable): " + B.VALID_FORMS.replace("%", "%%"))
    g.addoption("--compare-strict", action="store_true",
                help="a protocol-hash or package-version mismatch with the baseline is an error")
    g.addoption("--degrade-encoder", metavar="NAME:FACTOR",
                help="TEST-ONLY: plant a regression: encoder NAME's pooled features become constant "
                     "(blind) on a fixed fraction FACTOR in (0, 1] of the held-out windows")


def degrade_features(features: dict, factor: float, frames, seed: int = 0, rows=None) -> dict:
    """Blind a fixed fraction `factor` of `frames` (global frame indices: the held-out windows):
    their pooled features become constant ones, which the wrapper's LayerNorm turns into zero
    tokens, so evaluation sees image tokens that training never saw (cf. zero_image "eval").
    {camera: (B, T, C)} -> same shapes, row i being global frame `rows[i]` (rows None: frame i,
    a whole suite's array); the input is not modified."""
    import torch

    frames = torch.as_tensor(frames, dtype=torch.long)
    order = torch.randperm(len(frames), generator=torch.Generator().manual_seed(seed))
    blinded = frames[order[: round(factor * len(frames))]]
    out = {}
    for camera, x in features.items():
        at = torch.arange(len(x)) if rows is None else torch.as_tensor(rows, dtype=torch.long)
        y = x.clone()
        y[torch.isin(at, blinded)] = 1.0
        out[camera] = y
    return out


def _parse_degrade(value: str) -> tuple[str, float]:
    name, _, factor = value.rpartition(":")
    try:
        f = float(factor)
    except ValueError:
        f = -1.0
    if not name or not 0.0 < f <= 1.0:
        raise pytest.UsageError(f"--degrade-encoder {value!r}: expected NAME:FACTOR with FACTOR in "
                                "(0, 1], e.g. dinov2_s:1.0")
    return name, f


def _check_degraded_encoder(degrade: tuple[str, float], encoders: tuple[str, ...]) -> None:
    """--degrade-encoder names an encoder of this run, else nothing would be degraded."""
    import difflib

    name, factor = degrade
    if name not in encoders:
        close = difflib.get_close_matches(name, encoders, n=1, cutoff=0.5)
        raise pytest.UsageError(
            f"--degrade-encoder {name}:{factor:g}: {name!r} is not an encoder of this run "
            f"({', '.join(encoders)}), so nothing would be degraded; fix: --degrade-encoder "
            f"{close[0] if close else encoders[0]}:{factor:g}")


@dataclass(frozen=True)
class BaselineOptions:
    """The regression options of one run, parsed and checked at start-up (bench.options)."""

    dir: Path = DEFAULT_BASELINE_DIR
    compare_name: str | None = None
    save_name: str | None = None
    strict: bool = False
    compare_fail: tuple[str, ...] = ()
    degrade: tuple[str, float] | None = None  # (encoder, factor): --degrade-encoder

    @classmethod
    def parse(cls, config: pytest.Config, executor: str) -> BaselineOptions:
        """From the command line; a UsageError naming the option for a bad combination."""
        opt = config.getoption
        options = cls(Path(opt("--baseline-dir") or DEFAULT_BASELINE_DIR), opt("--compare"),
                      opt("--save-baseline"), bool(opt("--compare-strict")),
                      tuple(opt("--compare-fail") or ()),
                      _parse_degrade(opt("--degrade-encoder")) if opt("--degrade-encoder") else None)
        from bench.outputs import baseline_refusal

        replace = bool(opt("--replace-baseline"))
        problem = None
        if options.save_name is not None:
            problem = baseline_refusal("--save-baseline", options.save_name, options.dir, replace)
        elif replace:
            problem = ("--replace-baseline: it lets --save-baseline replace a saved baseline, and "
                       "--save-baseline is not given; fix: add --save-baseline NAME or drop it")
        needs_compare = (options.compare_fail or options.strict) and not options.compare_name
        if problem is None and needs_compare:
            problem = "--compare-fail / --compare-strict need --compare NAME"
        elif problem is None and options.degrade and executor != "local":
            problem = "--degrade-encoder acts on this process's workspace: it needs --executor local"
        elif problem is None and options.degrade and options.save_name:
            problem = ("--degrade-encoder plants a regression: never save it as a baseline (drop "
                       "--save-baseline)")
        if problem:
            raise pytest.UsageError(problem)
        return options


class BaselineRun:
    """This session's baseline work: what to save, what to compare with, and what happened."""

    def __init__(self, options: BaselineOptions, protocol_hash: str, profile=None) -> None:
        self.dir = options.dir
        self.strict = options.strict
        self.compare_name = options.compare_name
        self.save_name = options.save_name
        self.degrade = options.degrade
        if self.degrade is not None and profile is not None:
            _check_degraded_encoder(self.degrade, profile.encoders)
        self.warned: set[str] = set()
        self.comparison: B.Comparison | None = None
        self.saved: tuple[Path, int, list[str]] | None = None
        self.not_saved: str | None = None  # why --save-baseline wrote nothing
        self.checks: list = []
        self.baseline: B.Baseline | None = None
        try:
            self.checks = [B.parse_compare_fail(s) for s in options.compare_fail]
            # a name, checked at start-up (bench.outputs): never a path
            self.save_path = self.dir / f"{self.save_name}.json" if self.save_name else None
            if self.compare_name:
                self.compare_path = B.baseline_path(self.dir, self.compare_name)
                self.baseline = B.load_baseline(self.compare_path)
        except B.BaselineError as e:
            raise pytest.UsageError(str(e)) from None
        if self.baseline is not None and self.strict:
            if protocol_hash not in (self.baseline.protocol_hashes or []):
                raise pytest.UsageError(
                    f"--compare-strict: this run's protocol {protocol_hash} differs from baseline "
                    f"{self.compare_path}'s {self.baseline.protocol_hashes}; rerun with "
                    "--save-baseline after a deliberate protocol change")

    # -- per cell (in the process that runs the case) -----------------------------------------

    def degrades(self, cell) -> bool:
        return self.degrade is not None and cell.encoder == self.degrade[0]

    def feature_transform(self, cell, workspace: Callable):
        """With --degrade-encoder, the degradation a cell of that encoder is measured under
        (its plan's CellContext: bench.cell.plan; such a record is never resumed), else None."""
        if not self.degrades(cell):
            return None
        name, factor = self.degrade
        ws = workspace()

        def degrade(feats, rows=None):
            return degrade_features(feats, factor, ws.split(cell.suite).windows, rows=rows)

        degrade.description = f"degraded {name}:{factor}"  # recorded by the runner
        return degrade

    def check_cell(self, cell, record) -> None:
        """Fail the case (one line) on a cell-scope regression against the baseline."""
        if self.baseline is None or cell.id not in self.baseline.cells:
            return
        base = self.baseline.cells[cell.id]
        mismatch = B.provenance_mismatch(base, self.baseline, record)
        if mismatch and self.strict:
            pytest.fail(f"{cell.id}: not compared with baseline {self.compare_name}: "
                        f"{', '.join(mismatch)} (--compare-strict)", pytrace=False)
        for m in mismatch:
            if m not in self.warned:
                self.warned.add(m)
                warnings.warn(BaselineMismatchWarning(
                    f"baseline {self.compare_name}: {cell.id} (and maybe others) measured with "
                    f"{m}; compared anyway, --compare-strict makes this an error"))
        failures = B.cell_failures(base, record, self.checks)
        if failures:
            pytest.fail("; ".join(failures), pytrace=False)

    # -- session end (controller) --------------------------------------------------------------

    def finish(self, ids: list[str], records: dict) -> list[tuple[str, str]]:
        """Compare and / or save; the report sections the comparison adds."""
        if not ids:
            return []
        sections = []
        if self.baseline is not None:
            self.comparison = B.compare_run(self.compare_name, self.baseline, ids, records,
                                            self.checks)
            sections.append((f"Against baseline {self.compare_name}",
                             B.markdown_section(self.comparison, self.compare_path)))
        if self.save_path is not None:
            from bench.results.provenance import git_commit
            from bench.results.jsonfile import atomic_write_json

            kept = [records[c] for c in ids
                    if c in records and not records[c].measured.feature_transform]
            if not kept:  # an empty snapshot would overwrite a baseline with less than it held
                self.not_saved = (f"baseline {self.save_name} NOT saved: none of the "
                                  f"{len(ids)} selected cell(s) has a finished record; "
                                  f"{self.save_path} left as it was")
                return sections
            machine = {"node": platform.node(), "machine": platform.machine(),
                       "system": platform.system(), "python": platform.python_version()}
            data = B.snapshot(kept, self.save_name, git_commit=git_commit(), machine=machine,
                              created=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"))
            atomic_write_json(self.save_path, data.to_json())
            self.saved = (self.save_path, len(kept), [c for c in ids if c not in records])
        return sections

    @property
    def rank_flipped(self) -> bool:
        return self.comparison is not None and bool(self.comparison.flips)

    def summary(self, tr) -> None:
        if self.comparison is None and self.saved is None and self.not_saved is None:
            return
        tr.write_sep("-", "graftbench baseline")
        comp = self.comparison
        if comp is not None:
            tr.write_line(f"against {self.compare_name} ({self.compare_path}): {len(comp.rows)} "
                          f"compared, {len(comp.regressed)} regressed, {len(comp.flips)} rank "
                          f"flip(s), {len(comp.new)} new, {len(comp.not_compared)} not compared")
            for row in comp.regressed:
                tr.write_line("REGRESSED " + "; ".join(row.failures), red=True)
            for message in comp.flips.values():
                tr.write_line("RANK FLIP " + message, red=True)
            for row in comp.mismatched:
                tr.write_line(f"measured differently: {row.cell_id}: {', '.join(row.mismatch)}",
                              yellow=True)
            if comp.new:
                tr.write_line(f"new (not in baseline): {', '.join(comp.new)}")
            if comp.not_compared:
                tr.write_line(f"not compared: {', '.join(comp.not_compared)}")
        if self.not_saved is not None:
            tr.write_line(self.not_saved, red=True)
        if self.saved is not None:
            path, n, missing = self.saved
            tr.write_line(f"baseline {self.save_name} saved: {path} ({n} cells"
                          + (f"; no record for {', '.join(missing)})" if missing else ")"))
