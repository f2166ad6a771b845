#!/bin/bash
# The CPU training runs, evaluations and reports behind docs/results.md, in order (many hours
# on one core); run from the repo root after
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
# Surgery from the privileged state, --net small: cpu preset (sigma ceiling 0.05 -> 0.005 over
# 100k steps; state v2, unsafe penalty 0.3, bounded mean, staggered episodes, workspace ball,
# statistics frozen at 30k; w5 = 50 per rad), 3 seeds, 84k steps, then each continued to 100k
# steps, where the sigma ceiling reaches its 0.005 floor (docs/results/surgery/).
for s in 0 1 2; do
  $S train --task surgery --algo ppo --obs-mode state --seed $s --steps 84000 \
      --out runs/surg-state-w5-s$s
  [ -d runs/surg-state-w5-s$s-100k ] || cp -r runs/surg-state-w5-s$s runs/surg-state-w5-s$s-100k
  $S train --task surgery --algo ppo --obs-mode state --seed $s --steps 100000 --resume \
      --out runs/surg-state-w5-s$s-100k
done
# ... the lean net (small convs, [256, 128, 64] ReLU trunk), 120k steps, ~28 CPU min each
# (docs/results/surgery-lean/).
for s in 0 1 2; do
  $S train --task surgery --algo ppo --obs-mode state --net lean --seed $s --steps 120000 \
      --out runs/surg-state-lean-s$s
  $S eval --run runs/surg-state-lean-s$s --protocol idt --envs 50
  $S eval --run runs/surg-state-lean-s$s --protocol odt-patient --envs 50
done
# ... and with the distance penalty for unsafe steps (docs/envs.md): Table 1's state row, every
# target met by every seed in <= 30 CPU min (docs/results/surgery-dist/).
for s in 0 1 2; do
  $S train --task surgery --algo ppo --obs-mode state --net lean \
      --env-option unsafe_distance_penalty=100 --seed $s --steps 120000 --out runs/surg-state-dist-s$s
  $S eval --run runs/surg-state-dist-s$s --protocol idt --envs 50
  $S eval --run runs/surg-state-dist-s$s --protocol odt-patient --envs 50
done
# Surgery from the paper's observation (US volume pooled 2x to 5 x 25 x 18, + tracked pose),
# PPO trained for the safety filter (the filter acts at test time only), cpu preset
# (w5 = 50), 51,968 steps (~98 CPU min); every schedule is fixed in steps, so this ends at the
# checkpoint of a longer run with the same settings.
$S train --task surgery --algo ppo-sf --obs-downsample 2 --steps 51968 --seed 0 \
    --out runs/surg-img-w5-s0
# Across a population: PPO navigation on the 32 population phantoms (seeds 100-131, apart
# from the held-out seeds 5-99), ~100 min; tested on them, on held-out phantoms 5-9 and on the
# real TotalSegmentator subject.
$S train --task navigation --algo ppo --preset cpu --patients 100-131 --steps 58000 --seed 0 \
    --out runs/nav-pop32-s0
$S eval --run runs/nav-pop32-s0 --envs 50
$S eval --run runs/nav-pop32-s0 --envs 50 --protocol odt-patient --held-out 5
$S eval --run runs/nav-pop32-s0 --envs 50 --patients tests/data/totalsegmentator_example \
    --name real-subject
# ... and with the probe's heading observed too (the transverse view is nearly
# mirror-symmetric); the schedule does not depend on --steps.
$S train --task navigation --algo ppo --preset cpu --patients 100-131 --steps 23168 --seed 0 \
    --obs-mode us_heading --out runs/nav-pop32-head-s0
$S eval --run runs/nav-pop32-head-s0 --envs 50
$S eval --run runs/nav-pop32-head-s0 --envs 50 --protocol odt-patient --held-out 5
$S eval --run runs/nav-pop32-head-s0 --envs 50 --patients tests/data/totalsegmentator_example \
    --name real-subject
# ... and with the lean net: the population result of docs/results.md (the documented run
# wrote a checkpoint every 2,944 steps and is reported at agent_26496.pt, its last within
# 120 min).
$S train --task navigation --algo ppo --preset cpu --patients 100-131 --steps 26496 --seed 0 \
    --obs-mode us_heading --net lean --out runs/nav-pop32-head-lean-s0
$S eval --run runs/nav-pop32-head-lean-s0 --envs 50
$S eval --run runs/nav-pop32-head-lean-s0 --envs 50 --protocol odt-patient --held-out 5
$S eval --run runs/nav-pop32-head-lean-s0 --envs 50 --patients tests/data/totalsegmentator_example \
    --name real-subject
# Imitation learning: expert datasets, ACT and Diffusion Policy (navigation at 100 x 75).
$S record --task navigation --preset mb --episodes 200 --envs 16 --out runs/ds-nav-mb
$S il-train --policy act --data runs/ds-nav-mb --image-size 100x75 --steps 75000 --threads 1 \
    --out runs/il-nav-act
# ... continued to 90 min of training in all (constant learning rate, so a resume is exact).
$S il-train --policy act --data runs/ds-nav-mb --out runs/il-nav-act --resume --steps 128000 \
    --threads 1
$S il-train --policy diffusion --data runs/ds-nav-mb --image-size 100x75 --steps 32000 \
    --threads 1 --out runs/il-nav-dp
# ... and on 1,000 episodes (the runs that meet the navigation targets), <= 90 CPU min each.
$S record --task navigation --preset mb --episodes 1000 --envs 16 --out runs/ds-nav-mb-1000
$S il-train --policy act --data runs/ds-nav-mb-1000 --image-size 100x75 --steps 128000 \
    --threads 1 --out runs/il-nav-act-1000
$S il-train --policy diffusion --data runs/ds-nav-mb-1000 --image-size 100x75 --steps 80000 \
    --threads 1 --out runs/il-nav-dp-1000
$S record --task surgery --preset mb --episodes 150 --envs 16 --out runs/ds-surg-mb
$S il-train --policy act --data runs/ds-surg-mb --steps 30000 --threads 1 --out runs/il-surg-act
# Seeds on Ray Tune: PPO navigation x 3 seeds and one A2C seed.
$S sweep --task navigation --algo ppo --seeds 3 --preset cpu --steps 2400 --max-concurrent 1 \
    --out runs/sweep-nav-ppo
$S sweep --task navigation --algo a2c --seeds 1 --preset cpu --steps 2400 --max-concurrent 1 \
    --out runs/sweep-nav-a2c

# 100-episode evaluations (eval seed 1000) per protocol.
$S eval --run runs/nav-ppo-small-s0 --protocol idt
$S eval --run runs/nav-ppo-small-s0 --protocol odt-patient
$S eval --run runs/nav-ppo-small-lb-s0 --protocol idt
$S eval --run runs/nav-ppo-small-lb-s0 --protocol odt-sim
$S eval --run runs/recon-ppo-small-s0 --protocol idt
for r in runs/surg-state-w5-s0 runs/surg-state-w5-s1 runs/surg-state-w5-s2 \
    runs/surg-state-w5-s0-100k runs/surg-state-w5-s1-100k runs/surg-state-w5-s2-100k \
    runs/surg-img-w5-s0 runs/il-surg-act; do
  $S eval --run $r --protocol idt --envs 50
  $S eval --run $r --protocol odt-patient --envs 50
done
$S eval --run runs/il-nav-act --trials 100 --envs 50
$S eval --run runs/il-nav-dp --trials 100 --envs 50
$S eval --run runs/il-nav-act-1000 --trials 100 --envs 50
$S eval --run runs/il-nav-act-1000 --trials 100 --envs 50 --seed 2000 --name idt-seed2000
$S eval --run runs/il-nav-dp-1000 --trials 100 --envs 50

# Tables and figures (from the saved episode logs and TensorBoard files only).
$S report --task navigation --runs runs/nav-ppo-small-s0 runs/nav-ppo-small-lb-s0 \
    --out docs/results/navigation
$S report --task reconstruction --runs runs/recon-ppo-small-s0 --out docs/results/reconstruction
$S report --task surgery --runs runs/surg-state-w5-s0-100k runs/surg-state-w5-s1-100k \
    runs/surg-state-w5-s2-100k runs/surg-img-w5-s0 runs/il-surg-act --out docs/results/surgery
$S report --task surgery --runs runs/surg-state-lean-s0 runs/surg-state-lean-s1 \
    runs/surg-state-lean-s2 runs/surg-img-w5-s0 --out docs/results/surgery-lean
$S report --task surgery --runs runs/surg-state-dist-s0 runs/surg-state-dist-s1 \
    runs/surg-state-dist-s2 runs/surg-img-w5-s0 --out docs/results/surgery-dist
$S plot --runs runs/sweep-nav-ppo/runs runs/sweep-nav-a2c/runs --out docs/results/navigation-sweep \
    --metric "Episode / return" --metric "Episode / position_error_mm"
$S plot --runs runs/nav-ppo-small-s0 --out docs/results/navigation-curves \
    --metric "Episode / return" --metric "Episode / position_error_mm"
# RL and IL side by side (navigation bars)
for s in 0 1 2; do $S eval --run runs/sweep-nav-ppo/runs/navigation-ppo-s$s --trials 100 --envs 50; done
$S report --task navigation --runs runs/sweep-nav-ppo/runs runs/il-nav-act-1000 runs/il-nav-dp-1000 \
    --out docs/results/navigation-il --no-curves
