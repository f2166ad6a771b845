"""Measure a task's ``EnvMemory`` constants (``sonogym.envs.footprint``) as its docstring says.

    python benchmarks/footprint.py [--tasks navigation surgery reconstruction] [--envs 4]

Each point is a fresh process (one torch thread) that imports sonogym, builds the task's env
with default options at 1 mm over 1 or 3 phantoms and takes three expert steps; it reports its
resident memory (VmRSS) and high-water mark (VmHWM) against the memory right after the import.
Run it twice: the first run also builds phantoms missing from the cache, whose peak is not the
env's. Prints per task: per patient (high-water-mark growth from 1 to 3 patients), the load
peak (what one patient's high-water mark leaves after ``BASE``, its envs and the patient) and
the resident growth per patient.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys


def _memory() -> dict[str, int]:
    text = open("/proc/self/status").read()
    return {k: int(re.search(rf"{k}:\s+(\d+)", text).group(1)) * 1024 for k in ("VmRSS", "VmHWM")}


def point(task: str, patients: int, envs: int) -> dict:
    """Memory of one env in this process (call in a fresh one)."""
    import torch

    torch.set_num_threads(1)
    import sonogym  # noqa: F401  (the import is the baseline)
    from sonogym.envs.policy import ExpertPolicy
    from sonogym.envs.registry import get_task, make_vec

    before = _memory()
    env = make_vec(task, envs, patients=tuple(range(patients)), phantom_spacing=0.001)
    policy = ExpertPolicy(env, get_task(task).expert)
    obs, info = env.reset(seed=0)
    for _ in range(3):
        obs, _, _, _, info = env.step(policy.act(obs, info))
    after = _memory()
    return {"rss": after["VmRSS"] - before["VmRSS"], "hwm": after["VmHWM"] - before["VmRSS"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["navigation", "surgery", "reconstruction"])
    ap.add_argument("--envs", type=int, default=4)
    ap.add_argument("--point", nargs=2, help=argparse.SUPPRESS)  # task, patients (child)
    a = ap.parse_args()
    if a.point:
        print(json.dumps(point(a.point[0], int(a.point[1]), a.envs)))
        return
    from sonogym.envs.footprint import BASE
    from sonogym.envs.registry import get_task

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    print("| task | per patient (HWM) MB | load peak MB | resident per patient MB |")
    print("|---|---:|---:|---:|")
    for task in a.tasks:
        m = {}
        for p in (1, 3):
            cmd = [sys.executable, __file__, "--envs", str(a.envs), "--point", task, str(p)]
            out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
            m[p] = json.loads(out.stdout.strip().splitlines()[-1])
        per_patient = (m[3]["hwm"] - m[1]["hwm"]) / 2
        per_env = get_task(task).memory.per_env
        load_peak = m[1]["hwm"] - BASE - per_env * a.envs - per_patient
        resident = (m[3]["rss"] - m[1]["rss"]) / 2
        figures = (per_patient, load_peak, resident)
        print(f"| {task} | " + " | ".join(f"{v / 1e6:.0f}" for v in figures) + " |")


if __name__ == "__main__":
    main()
