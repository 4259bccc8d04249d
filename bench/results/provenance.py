"""Where a number came from: versions, git commit, hardware, memory."""

from __future__ import annotations

import functools
import hashlib
import platform
import resource
import subprocess
import sys

import torch

from ondisk.paths import REPO_ROOT


def stable_seed(*parts: object) -> int:
    """A 31-bit seed from its parts, identical across processes (unlike hash())."""
    digest = hashlib.sha256(":".join(map(str, parts)).encode()).hexdigest()
    return int(digest[:8], 16) & 0x7FFFFFFF


@functools.cache
def versions() -> dict[str, str]:
    import lerobot
    import timm
    import transformers

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "lerobot": lerobot.__version__,
        "timm": timm.__version__,
        "transformers": transformers.__version__,
    }


@functools.cache
def git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"],
            capture_output=True, text=True, timeout=5,
        )
        commit = out.stdout.strip() or "unknown"
        dirty = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=5,
        ).stdout.strip()
        return commit + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what platform knows."""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def hardware() -> str:
    """GPU (if any), CPU model, the instruction set torch's CPU kernels use (AVX512 / AVX2 /
    ...: kernels move last bits across machines, docs/CI.md), cores and torch threads now."""
    try:
        import os

        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = torch.get_num_threads()
    cpu = (f"CPU {cpu_model()} ({torch.backends.cpu.get_cpu_capability()} kernels), {cores} "
           f"cores, torch threads {torch.get_num_threads()}, {sys.platform}")
    if torch.cuda.is_available():
        return f"{torch.cuda.get_device_name(0)} (CUDA {torch.version.cuda}); {cpu}"
    return cpu


def reset_peak_memory(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def peak_memory_mb(device: torch.device) -> dict[str, float]:
    """CUDA: peak allocated during the cell. CPU: the process's peak RSS so far (not per cell)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    out = {"process_peak_rss_mb": round(rss, 1)}
    if device.type == "cuda":
        out["cuda_peak_allocated_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
    return out
