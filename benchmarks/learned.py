"""Learned ultrasound benchmark: simulation time of the shipped nets and env-steps/s.

Prints two tables.

1. ``LearnedSimulator`` (shipped net 0; float32 and ``precision="bfloat16"``, "lrn-bf16") on
   1, 10 and 100 env images of 200 x 150 (the 2-D env
   image; the net runs on its 112 x 80 input grid and the output is resized back), CT slices
   of the seed-0 phantom at 1 mm: slice and simulate time per batch (median of --repeats after
   a warm-up), on CPU and on CUDA when present. Budget: 100 images <= 30 ms on one
   GPU (the paper: 111 ms for 100 on its GPU, 256 x 256, ~41 M-parameter nets).
2. Navigation env steps/s (US observations, KUKA arm, seeded random actions) of
   ``simulator="physical"`` (MB) and ``simulator="learned"`` (LB, all 5 nets, one line per
   --precisions), on CPU, for --env-counts envs. The simulators alternate within each of
   --rounds rounds (each times --steps steps after 2 warm-up steps), one process, so every
   round sees the same machine load; the load average is printed beside every timing.
   ``--baseline-src DIR`` (a ``src`` folder of another version, e.g. from ``git archive``)
   runs each round twice, in a fresh process on that code ("old") and on this checkout
   ("new"), alternating; the figures then include each process's env build.

    python benchmarks/learned.py [--threads 1] [--envs 1,10,100] [--env-counts 1,16]
    python benchmarks/learned.py --no-sim --env-counts 128 --threads 2 --rounds 5 \
        --baseline-src /tmp/old/src
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
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


ENV_SIMULATORS = {"MB": {"simulator": "physical"}}


def env_configs(precisions) -> dict[str, dict]:
    """Env settings by name: MB, then "LB <precision>" for each precision."""
    lb = {f"LB {p}": {"simulator": "learned", "learned_precision": p} for p in precisions}
    return {**ENV_SIMULATORS, **lb}


def env_rounds(n: int, steps: int, seed: int, precisions, rounds: int = 1) -> list[dict]:
    """Navigation envs of every config built once, then ``rounds`` times timed one after the
    other (``steps`` steps each, after 2 warm-up steps)."""
    from sonogym.envs.registry import make_vec

    envs = {}
    for name, kw in env_configs(precisions).items():
        envs[name] = make_vec("navigation", n, patients=(seed,), **kw)
        envs[name].reset(seed=0)
    space = next(iter(envs.values())).single_action_space
    low, high = torch.as_tensor(space.low), torch.as_tensor(space.high)
    gen = torch.Generator().manual_seed(0)
    for env in envs.values():
        for _ in range(2):
            env.step(low + (high - low) * torch.rand(n, low.shape[0], generator=gen))
    rows = []
    for r in range(rounds):
        for name, env in envs.items():
            acts = [low + (high - low) * torch.rand(n, low.shape[0], generator=gen)
                    for _ in range(steps)]  # fmt: skip
            load = os.getloadavg()[0]
            t0, c0 = time.perf_counter(), time.process_time()
            for a in acts:
                env.step(a)
            dt, dc = time.perf_counter() - t0, time.process_time() - c0
            rows.append({"round": r, "sim": name, "envs": n, "step_ms": 1e3 * dt / steps,
                         "cpu_ms": 1e3 * dc / steps, "env_steps_s": n * steps / dt,
                         "load": (load + os.getloadavg()[0]) / 2})  # fmt: skip
    return rows


def _round_in(src: str, args, n: int) -> list[dict]:
    """One round of ``env_rounds`` in a fresh process on the code in ``src``."""
    code = (
        "import json, sys, torch; sys.path.insert(0, sys.argv[1]); import learned as b; "
        "torch.set_num_threads(int(sys.argv[2])); "
        "print(json.dumps(b.env_rounds(int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]), "
        "sys.argv[6].split(','))))"
    )
    env = {**os.environ, "PYTHONPATH": src}
    argv = [os.path.dirname(os.path.abspath(__file__)), str(args.threads), str(n),
            str(args.steps), str(args.seed), ",".join(args.precisions)]  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code, *argv], env=env, check=True,
                         capture_output=True, text=True).stdout  # fmt: skip
    return json.loads(out.strip().splitlines()[-1])


def env_table(args) -> None:
    print(f"\n{'code':4} {'round':>5} {'simulator':12} {'envs':>5} {'step ms':>8} {'cpu ms':>7} "
          f"{'env-steps/s':>12} {'load':>5}")  # fmt: skip
    here = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "src")
    codes = [("new", here)] + ([("old", args.baseline_src)] if args.baseline_src else [])
    results: dict[tuple, list[float]] = {}

    def show(code: str, r: int, row: dict) -> None:
        results.setdefault((code, row["sim"], row["envs"]), []).append(row["env_steps_s"])
        print(f"{code:4} {r:5d} {row['sim']:12} {row['envs']:5d} {row['step_ms']:8.1f} "
              f"{row['cpu_ms']:7.1f} {row['env_steps_s']:12.1f} {row['load']:5.2f}",
              flush=True)  # fmt: skip

    for n in args.env_counts:
        if not args.baseline_src:
            for row in env_rounds(n, args.steps, args.seed, args.precisions, args.rounds):
                show("new", row["round"], row)
            continue
        for r in range(args.rounds):
            for code, src in codes:
                for row in _round_in(src, args, n):
                    show(code, r, row)
    print("\nmedians over rounds (ratio: LB / MB of the same code)")
    for (code, sim, n), v in results.items():
        mb = statistics.median(results[(code, "MB", n)])
        med = statistics.median(v)
        print(f"{code:4} {sim:12} {n:5d} envs: {med:7.1f} env-steps/s "
              f"(min {min(v):.1f}, max {max(v):.1f}), {med / mb:.2f} x MB")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ints = lambda s: [int(v) for v in s.split(",")]  # noqa: E731
    ap.add_argument("--envs", type=ints, default=[1, 10, 100], help="images per batch")
    ap.add_argument("--env-counts", type=ints, default=[1, 16], help="envs of the env table")
    ap.add_argument("--steps", type=int, default=20, help="timed env steps per round")
    ap.add_argument("--rounds", type=int, default=3, help="rounds of the env table")
    ap.add_argument("--precisions", type=lambda s: s.split(","), default=["float32", "bfloat16"],
                    help="learned_precision values of the env table")  # fmt: skip
    ap.add_argument(
        "--baseline-src",
        default=None,
        help="src folder of a baseline version, run alternately in the env table",
    )
    ap.add_argument("--seed", type=int, default=0, help="phantom seed")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cpu-only", action="store_true")
    ap.add_argument("--no-env", action="store_true", help="skip the env table")
    ap.add_argument("--no-sim", action="store_true", help="skip the simulation table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load = " ".join(f"{v:.2f}" for v in os.getloadavg())
    print(f"learned ultrasound, 200 x 150 images, torch {torch.__version__}, {args.threads} CPU "
          f"threads, load average {load}, median of {args.repeats}")  # fmt: skip
    t0 = time.time()
    if not args.no_sim:
        simulation_table(args)
    if not args.no_env:
        env_table(args)
    print(f"{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
