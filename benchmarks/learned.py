"""Learned ultrasound benchmark: simulation time of the shipped nets and env-steps/s.

Prints two tables.

1. ``LearnedSimulator`` (shipped net 0; float32 and ``precision="bfloat16"``, "lrn-bf16") on
   1, 10 and 100 env images of 200 x 150 (the 2-D env
   image; the net runs on its 112 x 80 input grid and the output is resized back), CT slices
   of the seed-0 phantom at 1 mm: slice and simulate time per batch (median of --repeats after
   a warm-up), on CPU and on CUDA when present. Budget: 100 images <= 30 ms on one
   GPU (the paper: 111 ms for 100 on its GPU, 256 x 256, ~41 M-parameter nets).
2. Navigation env steps/s (``simulator="learned"``, all 5 nets, US observations, KUKA arm)
   next to ``simulator="physical"``, on CPU, for --env-counts envs: how slowly RL with the
   learned simulator runs on CPU.

    python benchmarks/learned.py [--threads 1] [--envs 1,10,100] [--env-counts 1,16]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

from common import surface_poses
from sonogym.anatomy import PhantomParams, load_phantom
from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer
from sonogym.ultrasound.learned.shipped import shipped_weights
from sonogym.ultrasound.learned.simulator import LearnedSimulator


def median_s(fn, repeats: int, sync) -> tuple[float, float]:
    fn()
    sync()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), min(ts)


def simulation_table(args) -> None:
    patient = load_phantom(args.seed, PhantomParams(spacing=1e-3))
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() and not args.cpu_only else [])
    print(f"{'device':7} {'sim':9} {'images':>6} {'slice ms':>9} {'simulate ms':>12} "
          f"{'(best)':>8} {'images/s':>9}")  # fmt: skip
    for dev in devices:
        sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
        slicer = Slicer([patient], ProbeGeometry.linear_2d(), device=dev)
        learned = LearnedSimulator(shipped_weights(0), device=dev)
        bf16 = LearnedSimulator(shipped_weights(0), device=dev, precision="bfloat16")
        physical = ModelBasedSimulator("physical", device=dev)
        for n in args.envs:
            pos, rot = surface_poses(patient, n)
            pos, rot = pos.float().to(dev), rot.float().to(dev)
            slices = slicer(pos, rot)
            t_slice, _ = median_s(lambda sl=slicer, p=pos, r=rot: sl(p, r), args.repeats, sync)
            for name, sim in (("learned", learned), ("lrn-bf16", bf16), ("physical", physical)):
                t, best = median_s(lambda sim=sim, s=slices: sim.simulate(s), args.repeats, sync)
                print(f"{dev:7} {name:9} {n:6d} {t_slice * 1e3:9.2f} {t * 1e3:12.2f} "
                      f"{best * 1e3:8.2f} {n / t:9.0f}")  # fmt: skip


def env_table(args) -> None:
    from sonogym.envs.registry import make_vec

    print(f"\n{'simulator':9} {'envs':>5} {'step ms':>9} {'env-steps/s':>12}")
    for n in args.env_counts:
        for sim in ("learned", "physical"):
            env = make_vec("navigation", n, simulator=sim, patients=(args.seed,))
            env.reset(seed=0)
            a = torch.zeros(n, 3)
            for _ in range(2):
                env.step(a)
            t0 = time.perf_counter()
            for _ in range(args.steps):
                env.step(a)
            dt = (time.perf_counter() - t0) / args.steps
            print(f"{sim:9} {n:5d} {dt * 1e3:9.1f} {n / dt:12.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ints = lambda s: [int(v) for v in s.split(",")]  # noqa: E731
    ap.add_argument("--envs", type=ints, default=[1, 10, 100], help="images per batch")
    ap.add_argument("--env-counts", type=ints, default=[1, 16], help="envs of the env table")
    ap.add_argument("--steps", type=int, default=20, help="timed env steps")
    ap.add_argument("--seed", type=int, default=0, help="phantom seed")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cpu-only", action="store_true")
    ap.add_argument("--no-env", action="store_true", help="skip the env table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"learned ultrasound, 200 x 150 images, torch {torch.__version__}, {args.threads} CPU "
          f"threads, load average {load}, median of {args.repeats}")  # fmt: skip
    t0 = time.time()
    simulation_table(args)
    if not args.no_env:
        env_table(args)
    print(f"{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
