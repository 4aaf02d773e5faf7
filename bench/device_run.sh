#!/usr/bin/env bash
# The GPU measurements of issue 34 as one call on a lent device machine (its image: python3 3.12
# with numpy, scipy, CuPy 14.2, threadpoolctl, tqdm, PyYAML; no ROS: these are the pure modules).
# Run from the repository root, e.g. through the device tool:
#     bash bench/device_run.sh               # everything goes to $OUT (or /tmp/sep-device) too
# Fits 8 minutes of wall time: each step has its own timeout and a failed step does not stop the
# next. Steps (timeouts, s):
#   0. the machine: nvidia-smi, CuPy, free memory; GPU utilization/memory sampled every 2 s
#      in the background (device_nvsmi.csv)
#   1. preflight (90): every CuPy call of the resident path, bandwidth, kernel compilation,
#      plate 256^2 / block 100^3 steps, and a small design + Monte Carlo, GPU against CPU
#   2. plate 256^2 (150): the design and a 100-run Monte Carlo on the GPU, per-stage table
#   3. block 100^3 = 10^6 states (what is left of TOTAL = 470 s, at least 120): the same, with the
#      default experiment plan 0.9 (about a third of the run-steps; BLOCK_PLAN=0.8 for 0.8.0's)
# A step that hits its timeout prints its sampled profile (where its time went) before it stops.
# A dry run without a GPU (the tests' emulator, small rows, short limits):
#     DEVICE=emulated PLATE_ROW=plate:64 BLOCK_ROW=block:24 TOTAL=200 bash bench/device_run.sh
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export PYTHONPATH=sep_plant:sep_estimator:sep_control PYTHONUNBUFFERED=1
export OPENBLAS_NUM_THREADS="${THREADS:-16}" OMP_NUM_THREADS="${THREADS:-16}"
out="${OUT:-/tmp/sep-device}"
mkdir -p "$out"
T0=$(date +%s)
stamp() { echo "=== $(date -u +%H:%M:%S) (+$(( $(date +%s) - T0 )) s) $*"; }
step() {   # step NAME TIMEOUT CMD...: run with a timeout, output tee'd to $out/device_NAME.txt
    local name=$1 limit=$2; shift 2
    stamp "$name (timeout ${limit} s): $*"
    timeout -k 10 "$limit" "$@" 2>&1 | tee "$out/device_$name.txt"
    local rc=${PIPESTATUS[0]}
    stamp "$name: exit $rc$([ "$rc" = 124 ] && echo ' (timed out)')"
    echo "$name $rc" >> "$out/device_exit_codes.txt"
}
{
    stamp "machine"
    nvidia-smi || true
    nvidia-smi --query-gpu=name,memory.total,memory.used,driver_version,clocks.max.sm --format=csv || true
    python3 -c "import sys, numpy, scipy; print(sys.version.split()[0], 'numpy', numpy.__version__, 'scipy', scipy.__version__)"
    nproc; free -g | head -2
    git log --oneline -1 2>/dev/null || true
} 2>&1 | tee "$out/device_machine.txt"
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 2 > "$out/device_nvsmi.csv" 2>&1 &
SMI=$!
DEVICE="${DEVICE:-cuda}"
step preflight "${PREFLIGHT_TIMEOUT:-90}" python3 bench/device_preflight.py $([ "$DEVICE" = emulated ] && echo --emulated)
step plate256 "${PLATE_TIMEOUT:-150}" python3 bench/bench_scale.py --device "$DEVICE" --rows "${PLATE_ROW:-plate:256}" --runs 100 \
    --threads "${THREADS:-16}" --log --json "$out/device_plate256.json"
left=$(( ${TOTAL:-470} - ($(date +%s) - T0) ))
step block100 "${BLOCK_TIMEOUT:-$(( left > 120 ? left : 120 ))}" python3 bench/bench_scale.py --device "$DEVICE" --rows "${BLOCK_ROW:-block:100}" --runs 100 \
    --threads "${THREADS:-16}" --experiment-plan "${BLOCK_PLAN:-0.9}" --log --json "$out/device_block100.json"
kill "$SMI" 2>/dev/null || true
stamp "done; exit codes:"; cat "$out/device_exit_codes.txt"
