#!/bin/bash
# The CPU training runs, evaluations and reports behind docs/agents.md ("CPU training runs")
# and docs/results.md. About 4 h on one core of a 2-core machine; run from the repo root after
# `make install`. Each step can be rerun alone; `sonogym train --resume` continues a run.
set -euo pipefail
S=".venv/bin/sonogym"
T="--envs 64 --seed 0 --net small --threads 1"
export OMP_NUM_THREADS=1

# Navigation, PPO from images (the documented run was stopped at its agent_9024.pt checkpoint).
$S train --task navigation --algo ppo $T --steps 9024 --obs-downsample 4 --out runs/nav-ppo-small-s0
# Navigation on the learned simulator, nets 0-3 (out-of-domain simulator protocol).
$S train --task navigation --algo ppo $T --steps 4512 --obs-downsample 4 --protocol odt-sim \
    --out runs/nav-ppo-small-lb-s0
# Reconstruction, submodular PPO.
$S train --task reconstruction --algo ppo $T --steps 4000 --out runs/recon-ppo-small-s0
# Surgery: equal-length PPO, PPO + safety filter, PPO-Lagrangian.
for a in ppo ppo-sf ppo-lag; do
  $S train --task surgery --algo $a $T --steps 6000 --out runs/surgery-$a-small-s0
done

# 100-episode evaluations (eval seed 1000) per protocol.
$S eval --run runs/nav-ppo-small-s0 --protocol idt
$S eval --run runs/nav-ppo-small-s0 --protocol odt-patient
$S eval --run runs/nav-ppo-small-lb-s0 --protocol idt
$S eval --run runs/nav-ppo-small-lb-s0 --protocol odt-sim
$S eval --run runs/recon-ppo-small-s0 --protocol idt
for a in ppo ppo-sf ppo-lag; do
  $S eval --run runs/surgery-$a-small-s0 --protocol idt
  $S eval --run runs/surgery-$a-small-s0 --protocol odt-patient
done

# Tables and figures (from the saved episode logs and TensorBoard files only).
$S report --task navigation --runs runs/nav-ppo-small-s0 runs/nav-ppo-small-lb-s0 \
    --out docs/results/navigation
$S report --task reconstruction --runs runs/recon-ppo-small-s0 --out docs/results/reconstruction
$S report --task surgery --runs runs/surgery-ppo-small-s0 runs/surgery-ppo-sf-small-s0 \
    runs/surgery-ppo-lag-small-s0 --out docs/results/surgery
$S plot --runs runs/nav-ppo-small-s0 --out docs/results/navigation-curves \
    --metric "Episode / return" --metric "Episode / position_error_mm"
