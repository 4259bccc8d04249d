#!/usr/bin/env bash
# Installs the optional LIBERO simulator (graftbench[libero]) into .venv: hf-libero, robosuite,
# mujoco and LIBERO's scene assets from the registry, the Debian GL libraries for headless
# rendering (EGL, OSMesa) when apt-get is usable, and LIBERO's config file (written without a
# prompt) under graftbench's cache dir. Idempotent. torch stays at constraints.txt's pin.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash scripts/install.sh

# Headless GL: libegl1 + libgl1-mesa-dri (MUJOCO_GL=egl, the default) and libosmesa6 (osmesa).
apt_packages=(libegl1 libgl1-mesa-dri libosmesa6)
missing=()
for pkg in "${apt_packages[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ "${#missing[@]}" -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        echo "[install_libero] apt-get install ${missing[*]}"
        # Not fatal: EGL alone renders (MUJOCO_GL=egl); a machine without an apt mirror goes on.
        { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq \
            "${missing[@]}" >/dev/null; } || echo "[install_libero] warning: apt-get could not" \
            "install ${missing[*]}; headless rendering may fail" >&2
    else
        echo "[install_libero] warning: missing Debian packages ${missing[*]} (need root + apt-get);" \
             "headless rendering may fail" >&2
    fi
fi

stamp=".venv/.graftbench-libero-installed"
want="$(sha256sum constraints.txt constraints-libero.txt pyproject.toml | sha256sum | cut -c1-16)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    # Both constraint files pin every package (torch 2.11.0 included); PIP_CONSTRAINT is cleared
    # so a machine-wide constraint cannot pull in another torch.
    PIP_CONSTRAINT= .venv/bin/python -m pip install -q -c constraints.txt -c constraints-libero.txt \
        -e ".[libero]"
    echo "$want" > "$stamp"
fi

# LIBERO's config (it prompts on stdin when none exists) and a check that a scene loads.
HF_HUB_OFFLINE=1 .venv/bin/python - <<'PY'
import torch
from bench.sim import env
env.configure()
print("[install_libero] LIBERO config:", env.write_libero_config() / "config.yaml")
print("[install_libero] assets:", env.assets_dir())
assert torch.__version__.startswith("2.11.0"), torch.__version__
print("[install_libero] done: torch", torch.__version__, "| MUJOCO_GL", __import__("os").environ["MUJOCO_GL"])
PY
