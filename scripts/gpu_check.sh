#!/usr/bin/env bash
# The checks that need a GPU, on the code as it is: the speed benchmarks on CUDA (each also
# times the CPU beside it) and a short training and evaluation with --device cuda. The tests
# never need a GPU; run this on a machine that has one, after `make install` (which installs
# pip's CUDA torch where nvidia-smi finds a GPU).
#
#   bash scripts/gpu_check.sh [OUT]      # OUT: where tables and the run go (default runs/gpu-check)
#
# Each step prints its table and saves it under OUT; a step that fails is reported and the
# next one runs. Exit status: the number of failed steps.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/gpu-check}
PY=${PY:-.venv/bin/python}
export PYTHONPATH=src
mkdir -p "$OUT"
if ! "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    echo "no CUDA device visible to torch: nothing to check here" >&2
    exit 1
fi
"$PY" -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name(0))" \
    | tee "$OUT/device.txt"
failed=0
step() {  # name, command...
    local name=$1; shift
    echo "== $name: $*"
    if ! "$@" > >(tee "$OUT/$name.txt") 2>&1; then
        echo "== $name FAILED" | tee -a "$OUT/$name.txt"
        failed=$((failed + 1))
    fi
}
step ultrasound "$PY" benchmarks/ultrasound.py --repeats 11 --save "$OUT/ultrasound.json"
step learned "$PY" benchmarks/learned.py --envs 1,10,100 --no-env
step envs "$PY" benchmarks/envs.py --envs 16 128 512 --device cuda cpu
step train-bench "$PY" benchmarks/train.py --presets paper cpu --envs 64 --steps 256 \
    --json "$OUT/train.json"
step train "$PY" -m sonogym.cli train --task navigation --algo ppo --device cuda --envs 128 \
    --steps 256 --seed 0 --force --out "$OUT/nav-ppo-cuda"
step eval "$PY" -m sonogym.cli eval --run "$OUT/nav-ppo-cuda" --device cuda --trials 100 \
    --envs 100
echo "== $failed step(s) failed; tables in $OUT"
exit "$failed"
