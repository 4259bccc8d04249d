"""scripts/gpu_smoke.sh: its --dry-run (CPU, tiny builds) end to end, its refusal without CUDA,
and the wheelhouse it installs from (pins, ignore rule; its build needs the registry: not here)."""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent
SMOKE_SH = ROOT / "scripts" / "gpu_smoke.sh"
SMOKE_PY = ROOT / "scripts" / "gpu_smoke.py"
WHEELHOUSE_SH = ROOT / "scripts" / "build_wheelhouse.sh"


def _env() -> dict:
    # One thread: the tiny ops are all thread overhead, and the cores are shared.
    return {**os.environ, "PYTHON": sys.executable, "OMP_NUM_THREADS": "1", "HF_HUB_OFFLINE": "1"}


@pytest.fixture(scope="module")
def dry_run() -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", str(SMOKE_SH), "--dry-run"], cwd=ROOT, env=_env(),
        capture_output=True, text=True, timeout=300,
    )


def _records(stdout: str) -> dict[str, dict]:
    records = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    return {record["backbone"]: record for record in records}


def test_dry_run_trains_and_samples_both_backbones(dry_run):
    assert dry_run.returncode == 0, dry_run.stderr[-3000:]
    records = _records(dry_run.stdout)
    assert sorted(records) == ["pi05", "smolvla"]
    for name, record in records.items():
        assert record["ok"], (name, record)
        assert (record["size"], record["device"], record["autocast"]) == ("tiny", "cpu", "off")
        assert record["steps"] == 5 and len(record["losses"]) == 5 == len(record["sec_per_step"])
        assert all(math.isfinite(v) for v in record["losses"]) and record["loss_finite"]
        assert record["projector_grad_finite"] and record["projector_moved"]
        assert record["sampled_finite"] and record["sampled_device"] == "cpu"
        assert record["sampled_shape"] == [2, record["chunk_size"], 7]
        # The graft: 768 encoder channels -> LM width, LayerNorm without affine, one Linear.
        assert record["projector_params"] == 768 * record["lm_width"] + record["lm_width"]
        assert record["peak_cuda_mem_gib"] is None and record["sec_per_step_after_first"] > 0


def test_dry_run_prints_one_human_line_per_backbone(dry_run):
    human = [line for line in dry_run.stdout.splitlines() if line.startswith("[gpu_smoke]")]
    assert [line.split()[1] for line in human] == ["smolvla", "pi05"]
    assert all(": ok;" in line and "s/step" in line for line in human), human


@pytest.mark.skipif(torch.cuda.is_available(), reason="the refusal is for machines without CUDA")
def test_refuses_in_one_line_without_cuda():
    for command in (["bash", str(SMOKE_SH)], [sys.executable, str(SMOKE_PY)]):
        done = subprocess.run(command, cwd=ROOT, env=_env(), capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 2, (command, done.stdout, done.stderr)
        assert done.stdout == ""
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and "refused" in lines[0] and "--dry-run" in lines[0], lines


def test_wheelhouse_packages_are_pinned_and_leave_torch_alone():
    text = WHEELHOUSE_SH.read_text()
    block = re.search(r"^PACKAGES=\((.*?)^\)", text, re.S | re.M).group(1)
    names = [word for line in block.splitlines() for word in line.split("#")[0].split()]
    pins = {
        line.split("==")[0].lower(): line.split("==")[1].strip()
        for line in (ROOT / "constraints.txt").read_text().splitlines() if "==" in line
    }
    assert "lerobot" in names and len(names) == len(set(names))
    assert [n for n in names if n.lower() not in pins] == []
    assert not [n for n in names if re.match(r"(torch|nvidia|triton|numpy)", n.lower())]


def test_wheelhouse_is_ignored_and_the_gpu_command_is_documented():
    ignored = subprocess.run(["git", "check-ignore", "-q", ".graftbench/wheels/x.whl"], cwd=ROOT)
    assert ignored.returncode == 0, ".graftbench/wheels/ must be in .gitignore"
    header = SMOKE_SH.read_text().split("set -euo pipefail")[0]
    assert 'run(command="bash scripts/gpu_smoke.sh", carry=[".graftbench/wheels"]' in header
    assert "bash scripts/build_wheelhouse.sh" in header
