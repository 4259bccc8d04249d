"""CI regression mode as pytest hooks: `--save-baseline`, `--compare`, `--compare-fail`.

Hooks only hand work on to one `BaselineRun` (kept in `config.stash`); the logic is bench.baseline.
- cell checks (`mse:10%`, ...) run right after each grid case's body, on the record the case just
  stored, and fail THAT case with a one-line message;
- rank checks need every cell of a group, so they run once at session end (controller), over the
  store: flipped groups are listed in the terminal summary and REPORT.md, and the exit status
  becomes non-zero;
- the "Against baseline NAME" REPORT.md section is appended before bench.plugin builds the report.
"""

from __future__ import annotations

import datetime as dt
import platform
import sys
import warnings
from pathlib import Path

import pytest

from bench import baseline as B
from bench.cells import CellSpec
from bench.paths import REPO_ROOT
from bench.plugin import SESSION_KEY

DEFAULT_BASELINE_DIR = REPO_ROOT / ".graftbench" / "baselines"
CELL_PARAMS = ("graft_cell", "control_cell")
USER_PROPERTY = "graftbench_cell"


class BaselineMismatchWarning(pytest.PytestWarning):
    """The run and the baseline were measured under a different protocol or package versions."""


def pytest_addoption(parser: pytest.Parser) -> None:
    g = parser.getgroup("graftbench-baseline", "graftbench CI regression mode")
    g.addoption("--save-baseline", metavar="NAME",
                help="at session end, snapshot the selected cells' stored records as baseline NAME")
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


def degrade_features(features: dict, factor: float, frames, seed: int = 0) -> dict:
    """Blind a fixed fraction `factor` of `frames` (global frame indices: the held-out windows):
    their pooled features become constant ones, which the wrapper's LayerNorm turns into zero
    tokens, so evaluation sees image tokens that training never saw (cf. zero_image "eval").
    {camera: (N_frames, T, C)} -> same shapes; the input is not modified."""
    import torch

    frames = torch.as_tensor(frames, dtype=torch.long)
    order = torch.randperm(len(frames), generator=torch.Generator().manual_seed(seed))
    blinded = frames[order[: round(factor * len(frames))]]
    out = {}
    for camera, x in features.items():
        y = x.clone()
        y[blinded] = 1.0
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


def _cell_of(item: pytest.Item):
    params = getattr(getattr(item, "callspec", None), "params", {})
    for name in CELL_PARAMS:
        if isinstance(params.get(name), CellSpec):  # an empty grid parametrises with NOTSET
            return params[name]
    return None


class BaselineRun:
    """This session's baseline work: what to save, what to compare with, and what happened."""

    def __init__(self, config: pytest.Config) -> None:
        opt = config.getoption
        self.config = config
        self.session = config.stash.get(SESSION_KEY, None)
        self.dir = Path(opt("--baseline-dir") or DEFAULT_BASELINE_DIR)
        self.strict = bool(opt("--compare-strict"))
        self.compare_name = opt("--compare")
        self.save_name = opt("--save-baseline")
        self.degrade = _parse_degrade(opt("--degrade-encoder")) if opt("--degrade-encoder") else None
        self.seen: list[str] = []  # grid cells reported in this session (controller side)
        self.warned: set[str] = set()
        self.comparison: B.Comparison | None = None
        self.saved: tuple[Path, int, list[str]] | None = None
        self.checks: list = []
        self.baseline: dict | None = None
        try:
            specs = opt("--compare-fail")
            if (specs or self.strict) and not self.compare_name:
                raise B.BaselineError("--compare-fail / --compare-strict need --compare NAME")
            if self.degrade and config.getoption("--executor", "local") != "local":
                raise B.BaselineError("--degrade-encoder acts on this process's workspace: it "
                                      "needs --executor local")
            if self.degrade and self.save_name:
                raise B.BaselineError("--degrade-encoder plants a regression: never save it as a "
                                      "baseline (drop --save-baseline)")
            self.checks = [B.parse_compare_fail(s) for s in specs]
            self.save_path = B.baseline_path(self.dir, self.save_name) if self.save_name else None
            if self.compare_name:
                self.compare_path = B.baseline_path(self.dir, self.compare_name)
                self.baseline = B.load_baseline(self.compare_path)
        except B.BaselineError as e:
            raise pytest.UsageError(str(e)) from None
        if self.baseline is not None and self.strict and self.session is not None:
            now = self.session.profile.protocol.hash
            if now not in self.baseline.get("protocol_hashes", []):
                raise pytest.UsageError(
                    f"--compare-strict: this run's protocol {now} differs from baseline "
                    f"{self.compare_path}'s {self.baseline.get('protocol_hashes')}; rerun with "
                    "--save-baseline after a deliberate protocol change")

    # -- per cell (in the process that runs the case) -----------------------------------------

    def before_cell(self, cell) -> None:
        """Never resume a degraded record; with --degrade-encoder, always remeasure its cells."""
        store = self.session.store
        record = store.load(cell.id)
        degraded_now = self.degrade is not None and cell.encoder == self.degrade[0]
        if record is not None and (degraded_now or record.get("degraded")):
            store.cell_path(cell.id).unlink(missing_ok=True)
        if degraded_now:
            name, factor = self.degrade
            ws = self.session.workspace()
            ws.feature_transforms[name] = lambda feats: degrade_features(
                feats, factor, ws.split(cell.suite).windows)

    def after_cell(self, cell) -> None:
        """Mark degraded records, then fail the case on a cell-scope regression."""
        store = self.session.store
        record = store.load(cell.id)
        if record is None:
            return
        if self.degrade is not None and cell.encoder == self.degrade[0]:
            record["degraded"] = f"{self.degrade[0]}:{self.degrade[1]}"
            store.write(record)
        if self.baseline is None or cell.id not in self.baseline["cells"]:
            return
        base = self.baseline["cells"][cell.id]
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

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        """Hook (this object is registered as a plugin): note the grid cells that reported."""
        if report.when == "setup":
            self.seen += [v for k, v in report.user_properties
                          if k == USER_PROPERTY and v not in self.seen]

    def selected(self) -> list[str]:
        chosen = list(self.session.selected) if self.session.selected else []
        return chosen + [c for c in self.seen if c not in set(chosen)]

    def records(self, ids: list[str]) -> dict[str, dict]:
        found = {cid: self.session.store.load(cid) for cid in ids}
        return {cid: r for cid, r in found.items() if r and r.get("status") == "ok"}

    def finish(self) -> None:
        ids = self.selected()
        if not ids:
            return
        records = self.records(ids)
        if self.baseline is not None:
            self.comparison = B.compare_run(self.compare_name, self.baseline, ids, records,
                                            self.checks)
            self.session.extra_sections.append(
                (f"Against baseline {self.compare_name}",
                 B.markdown_section(self.comparison, self.compare_path)))
        if self.save_path is not None:
            from bench.provenance import git_commit

            kept = [records[c] for c in ids if c in records and not records[c].get("degraded")]
            machine = {"node": platform.node(), "machine": platform.machine(),
                       "system": platform.system(), "python": platform.python_version()}
            data = B.snapshot(kept, self.save_name, git_commit=git_commit(), machine=machine,
                              created=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"))
            from bench.store import atomic_write_json

            atomic_write_json(self.save_path, data)
            self.saved = (self.save_path, len(kept), [c for c in ids if c not in records])

    def summary(self, tr) -> None:
        if self.comparison is None and self.saved is None:
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
        if self.saved is not None:
            path, n, missing = self.saved
            tr.write_line(f"baseline {self.save_name} saved: {path} ({n} cells"
                          + (f"; no record for {', '.join(missing)})" if missing else ")"))


RUN_KEY = pytest.StashKey[BaselineRun]()


def _run(config: pytest.Config) -> BaselineRun | None:
    run = config.stash.get(RUN_KEY, None)
    return run if run is not None and run.session is not None else None


@pytest.hookimpl(trylast=True)  # after bench.plugin has built the GraftSession
def pytest_configure(config: pytest.Config) -> None:
    run = BaselineRun(config)
    config.stash[RUN_KEY] = run
    config.pluginmanager.register(run, "graftbench-baseline-run")  # for its logreport hook


def pytest_collection_modifyitems(session, config, items) -> None:
    # The cell id travels with every report, so an xdist controller (which collects nothing)
    # still learns which cells ran.
    for item in items:
        cell = _cell_of(item)
        if cell is not None:
            item.user_properties.append((USER_PROPERTY, cell.id))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item):
    run, cell = _run(item.config), _cell_of(item)
    if run is None or cell is None:
        return (yield)
    run.before_cell(cell)
    result = yield  # re-raises when the body failed: that failure stands, nothing is compared
    run.after_cell(cell)
    return result


@pytest.hookimpl(tryfirst=True)  # before bench.plugin's sessionfinish builds REPORT.md
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    run = _run(session.config)
    if run is None or hasattr(session.config, "workerinput"):
        return
    try:
        run.finish()
    except Exception as e:  # a comparison that could not be made must not pass silently
        sys.stderr.write(f"\n[graftbench] baseline compare/save failed: {type(e).__name__}: {e}\n")
        session.exitstatus = pytest.ExitCode.INTERNAL_ERROR
        return
    if run.comparison is not None and run.comparison.flips and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    run = _run(config)
    if run is not None and not hasattr(config, "workerinput"):
        run.summary(terminalreporter)
