"""Env-steps per second and resident memory against patients x envs (many patients).

    python benchmarks/population.py [--task navigation] [--patients 1 8 32 64]
        [--envs 32 128 512] [--steps 20] [--phantom-spacing 0.001] [--threads 1]
        [--side-by-side 6] [--save pop.json] [--baseline old.json]

Each (patients, envs) point runs in a fresh process (so resident memory is that point's
alone): it builds ``make_vec(task, envs, patients=range(P))`` with the arm in the loop, takes
3 warm-up steps and ``--steps`` timed steps with random actions, and reports env-steps/s and
the process's resident memory (current and peak, from /proc; torch and the interpreter
included). "MB per extra patient" is the slope of resident memory over the patient counts at
the smallest env count. Points whose memory, extrapolated from the slope so far, would pass
``--mem-limit`` (default: 80 % of the machine's memory) are skipped and marked so, not run.
Phantoms are built once into the on-disk cache (the first run of a large P takes minutes).

"Side by side" is the figure a user reads in ``top``: in one process, an env over 1 patient and
then one over ``--side-by-side`` P patients (6 envs each, both alive, after a warm-up env on
another patient that pays the one-time costs); resident memory per extra patient is
((growth of the P-patient env) - (growth of the 1-patient env)) / (P - 1), printed next to the
slicer's crop per patient.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path


def measure(task: str, patients: int, envs: int, steps: int, spacing: float) -> dict:
    """One point, in this process."""
    import time

    import torch

    from sonogym.envs.registry import make_vec

    def rss_mb() -> float:
        return (
            int(Path("/proc/self/statm").read_text().split()[1])
            * os.sysconf("SC_PAGE_SIZE")
            / 2**20
        )

    def peak_mb() -> float:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    t0 = time.perf_counter()
    env = make_vec(task, envs, patients=tuple(range(patients)), phantom_spacing=spacing)
    env.reset(seed=0)
    build_s = time.perf_counter() - t0
    g = torch.Generator().manual_seed(0)
    low = torch.as_tensor(env.single_action_space.low)
    high = torch.as_tensor(env.single_action_space.high)

    def act():
        return low + (high - low) * torch.rand(envs, low.shape[0], generator=g)

    for _ in range(3):
        env.step(act())
    t1 = time.perf_counter()
    for _ in range(steps):
        env.step(act())
    dt = time.perf_counter() - t1
    return {
        "task": task,
        "patients": patients,
        "envs": envs,
        "env_steps_per_s": envs * steps / dt,
        "ms_per_step": 1e3 * dt / steps,
        "rss_mb": rss_mb(),
        "peak_rss_mb": peak_mb(),
        "build_s": build_s,
    }


def side_by_side(task: str, patients: int, spacing: float) -> dict:
    """Resident memory per extra patient with two envs alive in this process (module doc)."""
    import torch

    from sonogym.envs.registry import make_vec

    def rss_mb() -> float:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20

    def build(seeds):
        env = make_vec(task, 6, patients=tuple(seeds), phantom_spacing=spacing)
        env.reset(seed=0)
        env.step(torch.zeros(env.action_space.shape))
        return env

    warm = build([patients])  # pays imports, tables and scratch once
    r0 = rss_mb()
    one = build([0])
    r1 = rss_mb()
    many = build(range(patients))
    r2 = rss_mb()
    crop = (many.scene.slicer.nbytes - one.scene.slicer.nbytes) / (patients - 1) / 2**20
    del warm
    return {
        "patients": patients,
        "rss_per_extra_patient_mb": ((r2 - r1) - (r1 - r0)) / (patients - 1),
        "crop_per_patient_mb": crop,
    }


def run_point(args, patients: int, envs: int) -> dict:
    cmd = [
        sys.executable, __file__, "--point", args.task, str(patients), str(envs),
        str(args.steps), str(args.phantom_spacing), "--threads", str(args.threads),
    ]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    if out.returncode != 0:
        tail = out.stderr.strip().splitlines()[-1:] or ["(no output)"]
        return {"patients": patients, "envs": envs, "error": tail[0]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def mem_total_mb() -> float:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) / 1024
    return float("inf")


def slope(rows: list[dict], envs: int) -> float | None:
    """MB of resident memory per extra patient, from the points at ``envs`` envs."""
    pts = sorted((r["patients"], r["rss_mb"]) for r in rows if r["envs"] == envs and "rss_mb" in r)
    if len(pts) < 2 or pts[-1][0] == pts[0][0]:
        return None
    (p0, m0), (p1, m1) = pts[0], pts[-1]
    return (m1 - m0) / (p1 - p0)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--task", default="navigation")
    ap.add_argument("--patients", type=int, nargs="+", default=[1, 8, 32, 64])
    ap.add_argument("--envs", type=int, nargs="+", default=[32, 128, 512])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--phantom-spacing", type=float, default=0.001, help="m (default 1 mm)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--mem-limit", type=float, default=None, help="MB (default 80 %% of RAM)")
    ap.add_argument(
        "--side-by-side", type=int, default=6, metavar="P",
        help="patients of the one-process figure (0: skip it)",
    )  # fmt: skip
    ap.add_argument("--save", type=Path, help="write the figures to this JSON file")
    ap.add_argument("--baseline", type=Path, help="compare with figures saved by --save")
    ap.add_argument("--point", nargs=5, help=argparse.SUPPRESS)  # internal: one point
    ap.add_argument("--side-point", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.side_point:
        import torch

        torch.set_num_threads(args.threads)
        print(json.dumps(side_by_side(args.task, args.side_by_side, args.phantom_spacing)))
        return
    if args.point:
        import torch

        torch.set_num_threads(args.threads)
        task, p, n, steps, sp = args.point
        print(json.dumps(measure(task, int(p), int(n), int(steps), float(sp))))
        return
    limit = args.mem_limit or 0.8 * mem_total_mb()
    rows: list[dict] = []
    small = min(args.envs)
    for p in sorted(args.patients):
        for n in sorted(args.envs):
            s = slope(rows, small)
            base = next((r["rss_mb"] for r in rows if "rss_mb" in r and r["envs"] == n), None)
            first = next((r for r in rows if "rss_mb" in r and r["envs"] == n), None)
            if s is not None and base is not None and first is not None:
                predicted = base + s * (p - first["patients"])
                if predicted > limit:
                    rows.append({"patients": p, "envs": n, "skipped": f"~{predicted:.0f} MB"})
                    continue
            rows.append(run_point(args, p, n))
            print(json.dumps(rows[-1]), file=sys.stderr)
    load = os.getloadavg()
    header = (
        f"{args.task}, arm in the loop, phantoms at {args.phantom_spacing * 1e3:g} mm, "
        f"{args.threads} thread(s), {args.steps} steps, load average {load[0]:.1f}"
    )
    per_patient = slope(rows, small)
    baseline = json.loads(args.baseline.read_text())["rows"] if args.baseline else []
    old = {(r["patients"], r["envs"]): r for r in baseline if "rss_mb" in r}
    print(header)
    cols = "| patients | envs | env-steps/s | ms/step | RSS MB | peak MB | build s |"
    print(cols + (" steps/s vs base | RSS vs base |" if old else ""))
    print("|---" * (7 + (2 if old else 0)) + "|")
    for r in rows:
        if "rss_mb" not in r:
            why = r.get("skipped") and f"skipped: {r['skipped']} > limit" or r.get("error")
            print(f"| {r['patients']} | {r['envs']} | {why} |")
            continue
        line = (
            f"| {r['patients']} | {r['envs']} | {r['env_steps_per_s']:.0f} | "
            f"{r['ms_per_step']:.1f} | {r['rss_mb']:.0f} | {r['peak_rss_mb']:.0f} | "
            f"{r['build_s']:.1f} |"
        )
        b = old.get((r["patients"], r["envs"]))
        if b:
            line += (
                f" {r['env_steps_per_s'] / b['env_steps_per_s']:.2f}x | "
                f"{r['rss_mb'] / b['rss_mb']:.2f}x |"
            )
        print(line)
    if per_patient is not None:
        print(f"resident memory per extra patient ({small} envs, fresh processes): "
              f"{per_patient:.0f} MB")  # fmt: skip
    side = None
    if args.side_by_side > 1:
        cmd = [
            sys.executable, __file__, "--side-point", "--task", args.task,
            "--side-by-side", str(args.side_by_side), "--threads", str(args.threads),
            "--phantom-spacing", str(args.phantom_spacing),
        ]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        side = json.loads(out.stdout.strip().splitlines()[-1])
        print(
            f"resident memory per extra patient, side by side (1 and {side['patients']} "
            f"patients, 6 envs each, one process): {side['rss_per_extra_patient_mb']:.1f} MB "
            f"(slicer crop {side['crop_per_patient_mb']:.1f} MB per patient)"
        )
    if args.save:
        args.save.write_text(
            json.dumps(
                {
                    "header": header,
                    "per_patient_mb": per_patient,
                    "side_by_side": side,
                    "rows": rows,
                },
                indent=1,
            )  # fmt: skip
        )


if __name__ == "__main__":
    main()
