"""scripts/gpu_smoke.sh: its --dry-run (CPU, tiny builds) end to end, its refusal without CUDA,
and the wheelhouse it installs from (pins, ignore rule; its build needs the registry: not here)."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
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


@pytest.mark.slow  # the script in a fresh interpreter
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


@pytest.mark.slow
def test_dry_run_prints_one_human_line_per_backbone(dry_run):
    human = [line for line in dry_run.stdout.splitlines() if line.startswith("[gpu_smoke]")]
    assert [line.split()[1] for line in human] == ["smolvla", "pi05"]
    assert all(": ok;" in line and "s/step" in line for line in human), human


@pytest.mark.slow  # two fresh interpreters importing torch
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


FAKE_PYTHON = """#!/usr/bin/env bash
# A machine's python3 that sees CUDA: answers the CUDA probe, logs pip and the smoke script.
if [ "$1" = "-c" ]; then exit 0; fi
echo "$*" >> "$FAKE_LOG"
if [ "$1" = "scripts/gpu_smoke.py" ]; then echo "PYTHONPATH=$PYTHONPATH" >> "$FAKE_LOG"; fi
"""


def test_on_a_cuda_machine_it_installs_the_carried_wheelhouse_beside_the_machines_torch(tmp_path):
    """The GPU path, on a copy of the script with a stand-in python3 that sees CUDA: without
    wheels it names the build command; with them it installs them with --no-index --no-deps into
    a throwaway --target put on PYTHONPATH after the repo, never into the machine's packages."""
    (tmp_path / "scripts").mkdir()
    shutil.copy(SMOKE_SH, tmp_path / "scripts" / "gpu_smoke.sh")
    fake = tmp_path / "python3"
    fake.write_text(FAKE_PYTHON)
    fake.chmod(0o755)
    env = {**_env(), "PYTHON": str(fake), "FAKE_LOG": str(tmp_path / "log")}
    smoke = ["bash", str(tmp_path / "scripts" / "gpu_smoke.sh")]
    missing = subprocess.run(smoke, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2 and "bash scripts/build_wheelhouse.sh" in missing.stderr
    assert "carry .graftbench/wheels" in missing.stderr

    wheels = tmp_path / ".graftbench" / "wheels"
    wheels.mkdir(parents=True)
    (wheels / "lerobot-0.6.1-py3-none-any.whl").write_bytes(b"not really a wheel")
    done = subprocess.run(smoke, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    calls = (tmp_path / "log").read_text().splitlines()
    (pip,) = [c for c in calls if c.startswith("-m pip install")]
    assert "--no-index --no-deps" in pip and pip.endswith("lerobot-0.6.1-py3-none-any.whl")
    target = pip.split("--target ")[1].split()[0]
    assert calls[-2] == "scripts/gpu_smoke.py"
    assert calls[-1].startswith(f"PYTHONPATH={tmp_path}:{target}")  # the repo, then the wheels
    assert not Path(target).exists()  # thrown away at exit


def test_wheelhouse_is_ignored_by_git():
    ignored = subprocess.run(["git", "check-ignore", "-q", ".graftbench/wheels/x.whl"], cwd=ROOT)
    assert ignored.returncode == 0, ".graftbench/wheels/ must be in .gitignore"
