#!/usr/bin/env bash
# GPU smoke (issue 14): real-size, randomly initialised SmolVLA (450M) and pi0.5 (4.1B as LeRobot's
# default gemma_2b + gemma_300m builds it) on CUDA in bf16 autocast over float32 weights (as the
# harness runs real checkpoints; ~25 GiB peak expected): 5 projector steps of a graft (a random
# 768-channel feature grid pooled to the native 8x8 / 16x16 grid) and one sampled batch each,
# through graftbench's adapters. One JSON line and one human line per backbone
# (scripts/gpu_smoke.py).
#
# Exact use:
#   1. here, where pip reaches the registry:       bash scripts/build_wheelhouse.sh
#   2. on the GPU machine (python3 with torch, no lerobot, no network), as ONE command, with
#      the wheelhouse carried:
#        run(command="bash scripts/gpu_smoke.sh", carry=[".graftbench/wheels"], timeout_s=600)
#      It installs the wheels with --no-index --no-deps into a throwaway --target folder put on
#      PYTHONPATH ahead of the machine's site-packages (whose torch is never touched; no venv:
#      python3 there is itself a venv, and a venv of it would not see its torch), and it ends
#      within GPU_SMOKE_TIMEOUT_S
#      (default 540 s). Expected: ~2-4 min, mostly building pi0.5's random weights on the CPU
#      (62 s for a 1.9B-parameter one-layer build on one core here) and ~16 GiB of host memory.
#   CPU rehearsal of the same code path with the tiny architectures, no wheelhouse, the current
#   interpreter ($PYTHON, else .venv/bin/python, else python3):
#        bash scripts/gpu_smoke.sh --dry-run
# Extra arguments go to gpu_smoke.py (--backbones smolvla,pi05 --steps 5 --batch-size 2 ...).
set -euo pipefail
cd "$(dirname "$0")/.."
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 HF_DATASETS_OFFLINE=1 PYTHONUNBUFFERED=1

dry_run=0
for arg in "$@"; do
    if [ "$arg" = "--dry-run" ]; then dry_run=1; fi
done

if [ "$dry_run" = 1 ]; then
    python="${PYTHON:-}"
    if [ -z "$python" ]; then
        if [ -x .venv/bin/python ]; then python=.venv/bin/python; else python=python3; fi
    fi
    exec "$python" scripts/gpu_smoke.py "$@"
fi

python="${PYTHON:-python3}"
if ! reason="$("$python" -c '
import torch
print("" if torch.cuda.is_available() else f"torch {torch.__version__} sees no CUDA device")
' 2>&1)" || [ -n "$reason" ]; then
    echo "gpu_smoke: refused: ${reason##*$'\n'}; run it on a CUDA machine, or pass --dry-run" >&2
    exit 2
fi

wheels=.graftbench/wheels
if ! ls "$wheels"/*.whl >/dev/null 2>&1; then
    echo "gpu_smoke: no wheels in $wheels: run 'bash scripts/build_wheelhouse.sh' where pip" \
         "reaches the registry, then carry $wheels to this machine" >&2
    exit 2
fi
if [ -f "$wheels/SHA256SUMS" ]; then
    (cd "$wheels" && sha256sum --check --quiet SHA256SUMS)
fi
site="$(mktemp -d "${TMPDIR:-/tmp}/graftbench-smoke-site.XXXXXX")"
trap 'rm -rf "$site"' EXIT
started=$SECONDS
PIP_CONSTRAINT= "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --disable-pip-version-check --root-user-action=ignore --target "$site" "$wheels"/*.whl
# The repo first: some wheels ship a top-level `tests` package of their own.
export PYTHONPATH="$PWD:$site${PYTHONPATH:+:$PYTHONPATH}"
echo "[gpu_smoke] installed $(ls "$wheels"/*.whl | wc -l) wheels into $site in" \
     "$((SECONDS - started)) s; $(nvidia-smi --query-gpu=name,memory.total,driver_version \
     --format=csv,noheader 2>/dev/null || echo 'nvidia-smi unavailable')"

# What the machine itself brings, for reading a first failure (versions not carried here).
"$python" -m pip list --disable-pip-version-check 2>/dev/null \
    | grep -i -E '^(torch|numpy|pandas|pyarrow|fsspec|huggingface.hub|safetensors|accelerate) ' \
    | tr -s ' ' | paste -sd ';' | sed 's/^/[gpu_smoke] machine packages: /' || true

log=/dev/null
if [ -n "${OUT:-}" ] && [ -d "$OUT" ]; then log="$OUT/gpu_smoke.log"; fi
# SIGINT first: Python then prints where it was stuck before it goes.
set +e
timeout -s INT -k 20 "${GPU_SMOKE_TIMEOUT_S:-540}" "$python" scripts/gpu_smoke.py "$@" 2>&1 \
    | tee "$log"
status=${PIPESTATUS[0]}
set -e
if [ "$status" = 124 ]; then
    echo "gpu_smoke: stopped after ${GPU_SMOKE_TIMEOUT_S:-540} s (GPU_SMOKE_TIMEOUT_S)" >&2
fi
exit "$status"
