#!/usr/bin/env bash
# Rebuild the shipped learned-simulator nets (docs/learned_model_card.md): data for 5 nets,
# training (one net at a time, one CPU thread, ~6-8 min each), copying the weights into the
# package, and the model card's numbers. Usage: scripts/train_learned_nets.sh [WORK_DIR]
set -euo pipefail
WORK=${1:-runs/lb-recipe}
export OMP_NUM_THREADS=1
PY=${PYTHON:-python}
$PY -m sonogym.learned_training data  --work "$WORK"
$PY -m sonogym.learned_training train --work "$WORK"
$PY -m sonogym.learned_training ship  --work "$WORK"
$PY -m sonogym.learned_training card  --work "$WORK"
