#!/usr/bin/env bash
# Builds .graftbench/wheels/: the wheels scripts/gpu_smoke.sh installs on a GPU machine that has
# python3 with torch/timm/peft/transformers but no lerobot and no network (see gpu_smoke.sh).
# Run here, where pip reaches the registry:   bash scripts/build_wheelhouse.sh
#
# What goes in: lerobot and every package that importing lerobot's SmolVLA/pi0.5 policies and
# graftbench's adapters needs at import time and that such a machine lacks, plus transformers,
# tokenizers and peft at OUR pins (lerobot 0.6.1 needs transformers<5.6; that machine had 5.17
# and tokenizers 0.23.2, and peft reaches into transformers). Versions come from constraints.txt.
# Deliberately left out: torch and its CUDA wheels (the machine's own are used, never replaced),
# numpy (the machine's 2.5 stays: its compiled packages are built against it), and what that
# machine already has at a compatible version (huggingface_hub, safetensors, accelerate, pandas,
# pyarrow, opencv, ...). Every wheel is fetched with --no-deps, for CPython 3.12 on x86-64 Linux.
set -euo pipefail
cd "$(dirname "$0")/.."

WHEELS=.graftbench/wheels
LIMIT_MIB=60  # the whole travelling tree (tracked files + carried paths) must stay under 64 MiB
PACKAGES=(
    lerobot                              # the policies
    draccus mergedeep toml               # lerobot.configs (draccus and its own needs)
    gymnasium Farama-Notifications       # lerobot.envs.configs, imported by lerobot.configs.train
    datasets dill multiprocess           # lerobot.datasets.aggregate, via groot's processor
    pytz tzdata                          # pandas 2.x needs them (absent there, harmless for 3.x)
    av                                   # lerobot.datasets.depth_utils imports it at module level
    num2words                            # transformers' SmolVLMProcessor will not build without it
                                         # (its docopt is only for its CLI: not carried, sdist only)
    termcolor                            # a declared lerobot requirement the machine lacks
    transformers tokenizers peft         # our pins, replacing the machine's newer ones
)

python="${PYTHON:-}"
if [ -z "$python" ]; then
    if [ -x .venv/bin/python ]; then python=.venv/bin/python; else python=python3; fi
fi

pin() {  # the exact version constraints.txt pins for a package (names compared case-insensitively)
    local version
    version="$(grep -i -E "^$1==" constraints.txt | head -1 | cut -d= -f3)"
    if [ -z "$version" ]; then
        echo "[wheelhouse] $1 is not pinned in constraints.txt: pin it there first" >&2
        return 1
    fi
    echo "$version"
}

staging="$(mktemp -d "${TMPDIR:-/tmp}/graftbench-wheels.XXXXXX")"
trap 'rm -rf "$staging"' EXIT
specs=()
for name in "${PACKAGES[@]}"; do
    specs+=("$name==$(pin "$name")")
done
echo "[wheelhouse] downloading ${#specs[@]} wheels (--no-deps, cp312, manylinux x86_64) ..."
PIP_CONSTRAINT= "$python" -m pip download -q --no-deps --only-binary=:all: \
    --python-version 3.12 --implementation cp --abi cp312 --abi abi3 --abi none \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    --platform manylinux1_x86_64 --platform any \
    -d "$staging" "${specs[@]}" \
    2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)

# Exactly one wheel per package (two versions of one stop the whole install there), no torch.
count="$(find "$staging" -name '*.whl' | wc -l)"
if [ "$count" -ne "${#specs[@]}" ]; then
    echo "[wheelhouse] expected ${#specs[@]} wheels, got $count:" >&2
    ls "$staging" >&2
    exit 1
fi
if ls "$staging" | grep -i -E '^(torch|nvidia|triton|numpy)[-_]' >&2; then
    echo "[wheelhouse] refusing: the wheels above would replace the GPU machine's own stack" >&2
    exit 1
fi
total_kib="$(du -sk "$staging" | cut -f1)"
if [ "$total_kib" -gt $((LIMIT_MIB * 1024)) ]; then
    echo "[wheelhouse] $((total_kib / 1024)) MiB is over the ${LIMIT_MIB} MiB budget" >&2
    exit 1
fi

rm -rf "$WHEELS"
mkdir -p "$(dirname "$WHEELS")"
cp -r "$staging" "$WHEELS"
(cd "$WHEELS" && sha256sum -- *.whl > SHA256SUMS)
ls -l "$WHEELS"/*.whl | awk '{printf "  %8.1f KiB  %s\n", $5 / 1024, $NF}'
echo "[wheelhouse] $WHEELS: $count wheels, $(du -sh "$WHEELS" | cut -f1) in all" \
     "($(du -sb "$WHEELS" | cut -f1) bytes); carry it: run(carry=[\"$WHEELS\"], ...)"
