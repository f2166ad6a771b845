"""Model-based ultrasound benchmark: slice + simulate time and images/s, both ultrasound models.

Prints one table: for 1, 10, 100 and 400 envs, both models, on CPU (and on CUDA when present):
slice, simulate and total time per batch (median of --repeats, after one warm-up), images/s, and
the memory the patient, the slicer and the simulator hold. Budget: 100 images of
200 x 150, slice + simulate, <= 0.10 s on 2 CPU cores, <= 2 ms on one GPU, <= 300 MB per patient.

    python benchmarks/ultrasound.py                  # defaults: seed-0 phantom, 1 mm, 2 threads
    python benchmarks/ultrasound.py --save base.json # keep the figures ...
    python benchmarks/ultrasound.py --baseline base.json  # ... and compare a later run

Timings on a shared machine are only as good as its load: the header prints the load average,
"(best)" is the fastest total of the repeats and "CPU ms" the process CPU time of one total
(slice + simulate; summed over threads), which other tenants disturb much less than wall time.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import time
import warnings
from pathlib import Path

import torch

from common import surface_poses
from sonogym.anatomy import PhantomParams, load_phantom
from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer


def _time(fn, repeats: int, sync) -> tuple[list[float], list[float]]:
    """Wall-clock and process CPU seconds of ``repeats`` calls (after one warm-up)."""
    fn()
    sync()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def _bench(slicer, sim, pos, rot, probe, repeats: int, sync) -> list[float]:
    """Median seconds of slice, simulate and both, reusing output buffers as an env would."""
    slices = slicer(pos, rot)
    image = torch.empty(pos.shape[0], *probe.shape, device=pos.device)

    def slice_():
        slicer(pos, rot, out=slices)

    def simulate():
        sim.simulate(slices, out=image)

    def total():
        slice_()
        simulate()

    times = [_time(f, repeats, sync) for f in (slice_, simulate, total)]
    wall = [statistics.median(w) for w, _ in times]
    return [*wall, min(times[2][0]), statistics.median(times[2][1])]


def run(args) -> list[dict]:
    patient = load_phantom(args.seed, PhantomParams(spacing=args.spacing * 1e-3))
    probe = ProbeGeometry.linear_2d()
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() and not args.cpu_only else [])
    rows = []
    for dev in devices:
        sync = torch.cuda.synchronize if dev == "cuda" else (lambda: None)
        slicer = Slicer(patient, probe, device=dev)
        sim_bytes = 0
        for model in args.models:
            sim = ModelBasedSimulator(model, device=dev)
            for n in args.envs:
                pos, rot = surface_poses(patient, n)
                pos, rot = pos.to(dev), rot.to(dev)
                ts = _bench(slicer, sim, pos, rot, probe, args.repeats, sync)
                rows.append(
                    dict(
                        device=dev,
                        model=model,
                        envs=n,
                        slice_ms=ts[0] * 1e3,
                        simulate_ms=ts[1] * 1e3,
                        total_ms=ts[2] * 1e3,
                        images_per_s=n / ts[2],
                        best_total_ms=ts[3] * 1e3,
                        cpu_total_ms=ts[4] * 1e3,
                    )
                )
            sim_bytes = max(sim_bytes, sim.nbytes)
        mem = dict(
            patient_mb=patient.nbytes / 1e6,
            slicer_mb=slicer.nbytes / 1e6,
            simulator_mb=sim_bytes / 1e6,
        )
        rows[-1]["memory"] = mem
    return rows


def _key(row: dict) -> tuple:
    """(device, model, envs) of a row; figures saved before the rename name the model "preset"."""
    return row["device"], row.get("model", row.get("preset")), row["envs"]


def print_table(rows: list[dict], baseline: list[dict] | None, header: str) -> None:
    print(header)
    base = {_key(r): r for r in baseline or []}
    cols = "device  model     envs  slice ms  simulate ms  total ms  (best)  CPU ms   images/s"
    print(cols + ("  vs baseline" if baseline else ""))
    print("-" * (len(cols) + (13 if baseline else 0)))
    for r in rows:
        line = (
            f"{r['device']:<6}  {r['model']:<8} {r['envs']:>5}  {r['slice_ms']:>8.2f}  "
            f"{r['simulate_ms']:>11.2f}  {r['total_ms']:>8.2f} {r['best_total_ms']:>7.2f} "
            f"{r['cpu_total_ms']:>7.1f}  {r['images_per_s']:>9.0f}"
        )
        b = base.get(_key(r))
        if b:
            line += f"  {r['total_ms'] / b['total_ms']:>10.2f}x"
        print(line)


def _names(text: str) -> list[str]:
    return text.split(",")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--envs", type=lambda s: [int(v) for v in s.split(",")], default=[1, 10, 100, 400]
    )
    ap.add_argument("--models", type=_names, help="ultrasound models (default: reference,physical)")
    ap.add_argument("--presets", type=_names, help=argparse.SUPPRESS)  # the former --models
    ap.add_argument("--seed", type=int, default=0, help="phantom seed")
    ap.add_argument("--spacing", type=float, default=1.0, help="phantom voxel size, mm")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads (torch.set_num_threads)")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--cpu-only", action="store_true")
    ap.add_argument("--save", type=Path, help="write the figures to this JSON file")
    ap.add_argument("--baseline", type=Path, help="compare with figures saved by --save")
    args = ap.parse_args()
    if args.presets is not None:
        warnings.warn("--presets is deprecated: use --models", DeprecationWarning, stacklevel=1)
        if args.models not in (None, args.presets):
            ap.error("--presets (deprecated) and --models differ: give --models only")
        args.models = args.presets
    args.models = args.models or ["reference", "physical"]
    torch.set_num_threads(args.threads)
    t0 = time.time()
    rows = run(args)
    load = os.getloadavg()
    header = (
        f"model-based ultrasound, 200 x 150 images, seed-{args.seed} phantom at {args.spacing} mm, "
        f"torch {torch.__version__}, {args.threads} CPU threads, load average "
        f"{load[0]:.2f} {load[1]:.2f}, median of {args.repeats}"
    )
    baseline = json.loads(args.baseline.read_text())["rows"] if args.baseline else None
    print_table(rows, baseline, header)
    mem = rows[-1]["memory"]
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    print(
        f"memory per patient: volumes {mem['patient_mb']:.0f} MB + slicer copy "
        f"{mem['slicer_mb']:.0f} MB (float16 CT, labels, scratch) = "
        f"{mem['patient_mb'] + mem['slicer_mb']:.0f} MB; simulator tables + scratch "
        f"{mem['simulator_mb']:.0f} MB (shared by all patients); process peak RSS {rss:.0f} MB; "
        f"{time.time() - t0:.0f} s"
    )
    if args.save:
        args.save.write_text(json.dumps({"header": header, "rows": rows}, indent=1))
    if math.isnan(rows[0]["total_ms"]):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
