"""Two runs sharing a cache render a sim suite once (bench.sim.demos.generate holds the suite's
lock): the second waits for the first's suite and reuses it. No simulator needed: the attempts
and the dataset writer are replaced by stand-ins that record who ran them, and when."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from bench.progress import QUIET
from bench.sim import demos


def test_two_runs_on_one_cache_run_the_attempts_once(tmp_path, monkeypatch):
    running, overlaps, calls = [], [], []

    def attempts(spec, work, progress):
        running.append(1)
        overlaps.append(len(running))
        calls.append(threading.get_ident())
        time.sleep(0.3)
        running.pop()
        return {}

    def build(final, write):
        (final / "meta").mkdir(parents=True)
        (final / "meta" / "info.json").write_text("{}")
        return final

    monkeypatch.setattr(demos, "run_attempts", attempts)
    monkeypatch.setattr(demos, "expert_success", lambda spec, found: {})
    monkeypatch.setattr(demos, "build_dataset_dir", build)
    spec = SimpleNamespace(episodes_per_task=1, max_attempts=1)
    root = tmp_path / "spatial-suite"
    out = []
    runs = [threading.Thread(target=lambda: out.append(demos.generate(spec, root, QUIET)))
            for _ in range(2)]
    for run in runs:
        run.start()
    for run in runs:
        run.join()
    assert out == [root, root]
    assert len(calls) == 1 and overlaps == [1]
