#!/usr/bin/env bash
# Create ./.venv and install sonogym with its dev tools, Ray and the Rerun viewer
# (SONOGYM_EXTRAS=dev leaves out the optional ones: the viewer alone is ~750 MB).
# On a machine without an NVIDIA GPU the CPU build of torch is installed first, so that no
# dependency can pull the multi-GB CUDA build; on a GPU machine pip's normal torch is used.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
PIP=".venv/bin/python -m pip"
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
    if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
        $PIP install "torch>=2.6"
    else
        # The +cpu tag matters: without it pip may resolve the CUDA build from PyPI.
        $PIP install "torch==${SONOGYM_TORCH_VERSION:-2.13.0}+cpu" \
            || $PIP install "torch==${SONOGYM_TORCH_VERSION:-2.13.0}+cpu" \
                --index-url https://download.pytorch.org/whl/cpu
    fi
fi
$PIP install -e ".[${SONOGYM_EXTRAS:-dev,ray,viewer}]"
.venv/bin/python -c "import torch, sonogym; print('sonogym', sonogym.__version__, 'torch', torch.__version__)"
