"""What compressing the tissue under the probe costs an env step: the same task with and without
``contact_force``, interleaved in one process.

    python benchmarks/tissue_compression.py [--task navigation] [--envs 100] [--steps 10]
        [--rounds 5] [--force 10] [--threads 1] [--save out.json] [--baseline out.json]

Builds two envs of the task on the seed-0 phantom at 1 mm (``physical`` ultrasound, the KUKA
arm): one with static tissue, one pressed with ``--force`` newtons. Each round times ``--steps``
steps of both under the same seeded random actions, alternating which goes first; prints one
row per round and the medians: wall and process CPU time per step and their ratios pressed /
static, with the load average beside them (on a shared machine the CPU time is the steadier
figure). Budget (docs/ultrasound.md, "Tissue compression under the probe"): ratio <= 1.15.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from sonogym.envs.registry import make_vec


def timed_steps(env, steps: int, seed: int) -> tuple[float, float]:
    """(wall, process CPU) seconds per step of ``steps`` seeded random steps."""
    g = torch.Generator().manual_seed(seed)
    low = torch.as_tensor(env.single_action_space.low)
    high = torch.as_tensor(env.single_action_space.high)
    n = env.num_envs
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        env.step(low + (high - low) * torch.rand(n, low.shape[0], generator=g))
    return (time.perf_counter() - t0) / steps, (time.process_time() - c0) / steps


def loadavg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="navigation")
    ap.add_argument("--envs", type=int, default=100)
    ap.add_argument("--steps", type=int, default=10, help="steps per env and round")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--force", type=float, default=10.0, help="N, the pressed env's force")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--spacing", type=float, default=0.001, help="m, the phantom's voxels")
    ap.add_argument("--save", type=Path, help="write the figures to this JSON file")
    ap.add_argument("--baseline", type=Path, help="compare with figures saved by --save")
    args = ap.parse_args()
    if args.rounds < 3:
        ap.error("--rounds must be at least 3 (the figure is a median)")
    torch.set_num_threads(args.threads)
    kw = dict(patients=(0,), phantom_spacing=args.spacing)
    envs = {
        "off": make_vec(args.task, args.envs, **kw),
        "on": make_vec(args.task, args.envs, contact_force=args.force, **kw),
    }
    for env in envs.values():
        env.reset(seed=0)
        timed_steps(env, 2, seed=99)  # first-call allocations
    load_before = loadavg()
    rows = []
    for r in range(args.rounds):
        order = ("off", "on") if r % 2 == 0 else ("on", "off")
        t = {name: timed_steps(envs[name], args.steps, seed=r) for name in order}
        rows.append({
            "round": r, "off_ms": 1e3 * t["off"][0], "on_ms": 1e3 * t["on"][0],
            "ratio": t["on"][0] / t["off"][0], "off_cpu_ms": 1e3 * t["off"][1],
            "on_cpu_ms": 1e3 * t["on"][1], "cpu_ratio": t["on"][1] / t["off"][1],
        })  # fmt: skip
    load_after = loadavg()
    med = {k: statistics.median(row[k] for row in rows) for k in rows[0] if k != "round"}
    print(
        f"{args.task}, {args.envs} envs, {args.steps} steps x {args.rounds} rounds, "
        f"{args.force:g} N, torch {torch.__version__}, {args.threads} thread(s); "
        f"load average before {load_before}, after {load_after}"
    )
    print("| round | static ms/step | pressed ms/step | pressed / static | CPU ms static "
          "| CPU ms pressed | CPU pressed / static |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for row in [*rows, {"round": "median", **med}]:
        print(
            f"| {row['round']} | {row['off_ms']:.1f} | {row['on_ms']:.1f} | {row['ratio']:.3f} "
            f"| {row['off_cpu_ms']:.1f} | {row['on_cpu_ms']:.1f} | {row['cpu_ratio']:.3f} |"
        )
    if args.baseline:
        base = json.loads(args.baseline.read_text())["median"]
        print(f"baseline median ratio {base['ratio']:.3f} -> {med['ratio']:.3f} (wall), "
              f"{base['cpu_ratio']:.3f} -> {med['cpu_ratio']:.3f} (CPU)")  # fmt: skip
    if args.save:
        out = {"args": vars(args) | {"save": str(args.save), "baseline": str(args.baseline)},
               "load": [load_before, load_after], "rounds": rows, "median": med}  # fmt: skip
        args.save.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
