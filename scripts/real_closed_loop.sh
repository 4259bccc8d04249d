#!/usr/bin/env bash
# The real-encoder study's closed-loop tier, item by item (docs/real/closed_loop.toml says why
# these items); every item resumes from RESULTS, so a stopped run is continued by running this
# again. Usage: bash scripts/real_closed_loop.sh [RESULTS] [REPORT]
set -euo pipefail
results=${1:-.graftbench/results/real_loop}
report=${2:-docs/real/CLOSED_LOOP.md}
py=${PYTHON:-.venv/bin/python}
common=(--grid docs/real/closed_loop.toml --sim-tasks 0,1 --sim-demos 25 --sim-demo-noise 0.1
        --sim-demo-speed 0.5 --rollouts 10 --results-dir "$results" -p no:cacheprovider)
items=("--encoders blind --controls native -k native-seed0"
       "--encoders effnet_lite2 -k effnet_lite2-seed0"
       "--encoders effnet_lite0_random -k effnet_lite0_random-seed0"
       "--encoders effnet_lite0 -k effnet_lite0-seed0")
for item in "${items[@]}"; do
    echo "== $(date -u +%H:%M:%S) $item"
    # shellcheck disable=SC2086
    "$py" -m pytest bench "${common[@]}" $item
done
"$py" -m bench.report "$results" --out "$report"
