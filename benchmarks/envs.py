"""Env-steps per second with random actions (images included), CPU and CUDA when present.

    python benchmarks/envs.py [--envs 16 128] [--steps 50] [--device cpu]
        [--simulator learned --learned-precision bfloat16]

Prints one table. Budget: >= 500 env-steps/s for 128 navigation envs on 2 cores.
Phantom seed 0 at the default 1 mm; navigation with and without the arm in the loop. The last
column is a partial reset of one env in eight (an autoreset's cost), median of 5.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from sonogym.envs.registry import make_vec


def bench(task: str, n: int, steps: int, device: str, **kw) -> dict:
    env = make_vec(task, n, device=device, **kw)
    env.reset(seed=0)
    g = torch.Generator().manual_seed(0)
    low = torch.as_tensor(env.single_action_space.low)
    high = torch.as_tensor(env.single_action_space.high)

    def act():
        return (low + (high - low) * torch.rand(n, low.shape[0], generator=g)).to(device)

    for _ in range(3):
        env.step(act())
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        env.step(act())
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    dt = time.perf_counter() - t0
    mask = torch.zeros(n, dtype=torch.bool)
    mask[::8] = True
    resets = []
    for _ in range(5):
        t1 = time.perf_counter()
        env.reset(options={"reset_mask": mask})
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        resets.append(time.perf_counter() - t1)
    return {
        "ms/step": 1e3 * dt / steps,
        "env-steps/s": n * steps / dt,
        "reset ms": 1e3 * statistics.median(resets),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", type=int, nargs="+", default=[16, 128])
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--device", nargs="+", default=None)
    ap.add_argument("--simulator", default="physical")
    ap.add_argument("--learned-precision", default=None, help='"float32" or "bfloat16"')
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--tasks", nargs="+", default=["navigation", "reconstruction", "surgery"])
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = args.device or (["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
    rows = []
    for device in devices:
        for name in args.tasks:
            robots = ("kuka_med14", None) if name == "navigation" else ("default",)
            for robot in robots:
                kw = {} if robot == "default" else {"robot": robot}
                if args.learned_precision:
                    kw["learned_precision"] = args.learned_precision
                for n in args.envs:
                    r = bench(name, n, args.steps, device, simulator=args.simulator, **kw)
                    rows.append(
                        (device, name, str(robot), n, r["ms/step"], r["env-steps/s"], r["reset ms"])
                    )
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, simulator {args.simulator}"
    )
    print("| device | task | robot | envs | ms/step | env-steps/s | reset 1/8 ms |")
    print("|---|---|---|---|---|---|---|")
    for d, t, rb, n, ms, sps, rs in rows:
        print(f"| {d} | {t} | {rb} | {n} | {ms:.1f} | {sps:.0f} | {rs:.1f} |")


if __name__ == "__main__":
    main()
