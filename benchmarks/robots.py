"""Robot-arm benchmark: forward kinematics, Jacobian and one IK control step for N arms.

Prints one table: for 128 and 1024 arms of each model (KUKA LBR Med 14 and Franka FR3, probe
tool), on CPU (and on CUDA when present): FK time (tip and all link frames), FK + Jacobian time,
one control step of ``Arm.ik_step`` (default ``ArmConfig``: 2 DLS iterations, then the FK of the
reached pose; median and best), the same step in a control loop that passes ``result.q``
back as the envs do (the arm then reuses the last step's FK: one of three saved), and the
arm-steps per second the loop's median gives, each over --repeats runs after one warm-up.
Targets are reachable poses a few control steps away, so the step does real work.

    python benchmarks/robots.py                    # defaults: 2 threads, 128 and 1024 arms
    python benchmarks/robots.py --threads 1        # one thread (e.g. under pytest -n 2)
    python benchmarks/robots.py --save base.json   # keep the figures ...
    python benchmarks/robots.py --baseline base.json  # ... and compare a later run

Timings on a shared machine are only as good as its load: the header prints the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from sonogym.robots import Arm, ArmConfig


def _time(fn, repeats: int, sync) -> tuple[float, float]:
    """(median, best) seconds of fn over ``repeats`` runs after one warm-up."""
    fn()
    sync()
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        out.append(time.perf_counter() - t0)
    return statistics.median(out), min(out)


def run(args) -> list[dict]:
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() and not args.cpu_only else [])
    rows = []
    for dev in devices:
        sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
        for model in args.models:
            arm = Arm(ArmConfig(model=model), device=dev)
            for n in args.arms:
                g = torch.Generator().manual_seed(0)
                q = arm.random_joints(n, g, margin=0.3)
                step = (torch.rand(n, 7, generator=g) * 2 - 1).to(dev) * arm.max_joint_step * 3
                target_pos, target_rot = arm.fk(q + step)

                def fk(arm=arm, q=q):
                    arm.kinematics.frames(q)

                def jac(arm=arm, q=q):
                    arm.jacobian(q)

                def ik(arm=arm, q=q, tp=target_pos, tr=target_rot):
                    arm.ik_step(q, tp, tr)

                loop_q = [q]

                def loop(arm=arm, tp=target_pos, tr=target_rot, loop_q=loop_q):
                    loop_q[0] = arm.ik_step(loop_q[0], tp, tr).q

                (fk_s, _), (jac_s, _), (ik_s, ik_best), (loop_s, _) = (
                    _time(f, args.repeats, sync) for f in (fk, jac, ik, loop)
                )
                rows.append(
                    dict(
                        device=dev,
                        model=model,
                        arms=n,
                        fk_ms=fk_s * 1e3,
                        jacobian_ms=jac_s * 1e3,
                        ik_step_ms=ik_s * 1e3,
                        best_ik_step_ms=ik_best * 1e3,
                        loop_step_ms=loop_s * 1e3,
                        arm_steps_per_s=n / loop_s,
                    )
                )
    return rows


def print_table(rows: list[dict], baseline: list[dict] | None, header: str) -> None:
    print(header)
    base = {(r["device"], r["model"], r["arms"]): r for r in baseline or []}
    cols = "device  model        arms   FK ms  FK+Jac ms  IK step ms  (best)  loop ms  arm-steps/s"
    print(cols + ("  vs baseline" if baseline else ""))
    print("-" * (len(cols) + (13 if baseline else 0)))
    for r in rows:
        line = (
            f"{r['device']:<6}  {r['model']:<11} {r['arms']:>5}  {r['fk_ms']:>6.2f}  "
            f"{r['jacobian_ms']:>9.2f}  {r['ik_step_ms']:>10.2f} {r['best_ik_step_ms']:>7.2f}  "
            f"{r['loop_step_ms']:>7.2f}  {r['arm_steps_per_s']:>11.0f}"
        )
        b = base.get((r["device"], r["model"], r["arms"]))
        if b:
            line += f"  {r['ik_step_ms'] / b['ik_step_ms']:>10.2f}x"
        print(line)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--arms", type=lambda s: [int(v) for v in s.split(",")], default=[128, 1024])
    ap.add_argument("--models", type=lambda s: s.split(","), default=["kuka_med14", "franka_fr3"])
    ap.add_argument("--threads", type=int, default=2, help="CPU threads (torch.set_num_threads)")
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--cpu-only", action="store_true")
    ap.add_argument("--save", type=Path, help="write the figures to this JSON file")
    ap.add_argument("--baseline", type=Path, help="compare with figures saved by --save")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    rows = run(args)
    load = os.getloadavg()
    header = (
        f"robot arms (probe tool), median of {args.repeats}, torch {torch.__version__}, "
        f"{args.threads} CPU thread(s), load average {load[0]:.1f}"
    )
    baseline = json.loads(args.baseline.read_text())["rows"] if args.baseline else None
    print_table(rows, baseline, header)
    if args.save:
        args.save.write_text(json.dumps({"header": header, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
