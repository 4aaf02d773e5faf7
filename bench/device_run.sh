#!/usr/bin/env bash
# The GPU measurements of issue 9, as one call on a lent device machine (its image has python3
# 3.12 with numpy, scipy, CuPy 14.2, threadpoolctl, tqdm, PyYAML; no ROS is needed: these are
# the pure modules). Run from the repository root, e.g. through the device tool:
#     bash bench/device_run.sh            # writes $OUT/device_*.txt when OUT is set
# Step 1 (about a minute): batched steps, one CPU core vs the GPU, up to 10^6 states.
# Step 2 (the rest of the time limit): the design on the GPU for plate 256^2 and 1000^2.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
export PYTHONPATH=sep_plant:sep_estimator:sep_control PYTHONUNBUFFERED=1 OPENBLAS_NUM_THREADS=1
out="${OUT:-/tmp}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
python3 -c "import cupy; print('cupy', cupy.__version__, cupy.cuda.runtime.getDeviceCount(), 'device(s)')"
python3 bench/bench_plants.py --only-device --device cuda --repeats 3 2>&1 | tee "$out/device_plants.txt"
timeout "${SCALE_TIMEOUT:-420}" python3 bench/bench_scale.py --device cuda --rows plate:256 plate:1000 \
    --runs 100 --json "$out/device_scale.json" 2>&1 | tee "$out/device_scale.txt"
