"""Per-cell cost benchmarks (pytest-benchmark). Run them with:

    .venv/bin/pytest benchmarks --benchmark-only -p no:randomly

Files are named bench_*.py so that neither `pytest tests` nor `pytest bench` collects them; this
conftest collects them when `benchmarks/` is the target. Torch runs on ONE thread: on 2 shared
cores unpinned timings swung 30-100x. The session ends with the ratios the performance goals are
stated in (docs/PERFORMANCE.md), computed from this run's benchmark statistics.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"  # before torch starts its pools (if not imported yet)
os.environ["MKL_NUM_THREADS"] = "1"
os.environ.setdefault("GRAFTBENCH_QUIET", "1")
for _var in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE", "HF_DATASETS_OFFLINE"):
    os.environ[_var] = "1"

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)

# benchmark name -> {"steps": calls' steps, "frames"/"windows": units per call, stats}
COSTS_KEY = pytest.StashKey[dict]()
LOAD_KEY = pytest.StashKey[tuple]()  # os.getloadavg() when the session started


def pytest_collect_file(file_path, parent):
    if parent.session.isinitpath(file_path):
        return None  # named on the command line: pytest's python plugin collects it already
    if file_path.suffix == ".py" and file_path.name.startswith("bench_"):
        return pytest.Module.from_parent(parent, path=file_path)
    return None


def pytest_configure(config: pytest.Config) -> None:
    config.stash[COSTS_KEY] = {}
    config.stash[LOAD_KEY] = os.getloadavg()


@pytest.fixture
def record_cost(request, benchmark):
    """record_cost(key, **units): after `benchmark(...)`, keep its stats under `key` with the
    units one call covers (steps, frames, windows) for the end-of-session ratios."""
    costs = request.config.stash[COSTS_KEY]

    def record(key: str, **units) -> None:
        if benchmark.stats is None:  # --benchmark-disable: ran once, nothing measured
            return
        stats = benchmark.stats.stats
        benchmark.extra_info.update(units)
        costs[key] = {"min": stats.min, "median": stats.median, "rounds": stats.rounds, **units}

    return record


def per_unit(cost: dict, unit: str, stat: str) -> float:
    """Seconds per unit (per step, frame or window) of a recorded benchmark."""
    return cost[stat] / cost.get(unit, 1)


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    costs = config.stash.get(COSTS_KEY, {})
    if not costs:
        return
    tr = terminalreporter
    tr.write_sep("-", "graftbench per-cell costs (1 torch thread; min / median)")
    start = config.stash[LOAD_KEY]
    tr.write_line(f"{os.cpu_count()} cores; load average (1 min) {start[0]:.2f} at start, "
                  f"{os.getloadavg()[0]:.2f} at end: other work on the machine inflates medians")
    for key in sorted(costs):
        cost = costs[key]
        unit = next((u for u in ("steps", "frames", "windows") if u in cost), None)
        if unit is None:
            continue
        lo, mid = (per_unit(cost, unit, s) for s in ("min", "median"))
        tr.write_line(f"{key:<40} {lo * 1e3:9.2f} / {mid * 1e3:9.2f} ms per {unit[:-1]}"
                      + (f"  ({1 / mid:.1f} {unit}/s)" if unit == "windows" else ""))
    for backbone in sorted({k.split("/")[1] for k in costs if "/" in k}):
        lines = _ratios(costs, backbone)
        if lines:
            tr.write_sep("-", f"ratios, {backbone} (goal)")
            for line in lines:
                tr.write_line(line)


def _ratios(costs: dict, backbone: str) -> list[str]:
    def ratio(num: str, den: str, stat: str) -> float | None:
        a, b = costs.get(f"{num}/{backbone}"), costs.get(f"{den}/{backbone}")
        return per_unit(a, "steps", stat) / per_unit(b, "steps", stat) if a and b else None

    lines = []
    checks = [
        ("step_cached", "floor", "cached step / floor", "<= 1.2", lambda r: r <= 1.2),
        ("step_naive_siglip", "step_cached", "naive (tiny siglip) / cached", ">= 3",
         lambda r: r >= 3.0),
        ("step_naive_dinov2_s", "step_cached", "naive (tiny dinov2_s) / cached", ">= 3",
         lambda r: r >= 3.0),
        ("step_naive_dinov2_s_realsize", "step_cached", "naive (REAL-size dinov2_s) / cached",
         "info", None),
        ("realsize_step_cached", "realsize_floor", "REAL-size SmolVLA: cached step / floor",
         "<= 1.2", lambda r: r <= 1.2),
    ]
    for num, den, label, goal, met in checks:
        lo, mid = ratio(num, den, "min"), ratio(num, den, "median")
        if lo is None:
            continue
        verdict = "" if met is None else ("  met" if met(lo) else "  MISSED")
        lines.append(f"{label:<40} {lo:6.2f} (min) {mid:6.2f} (median)   goal {goal}{verdict}")
    return lines
