"""Wall time of a tiny training run and of one PPO update, per device preset.

    python benchmarks/train.py [--presets paper cpu] [--envs 4] [--steps 256] [--task navigation]
                               [--json out.json] [--baseline old.json]

The tiny run is what a new user starts with: ``sonogym train --task navigation --algo ppo
--envs 4 --steps 256`` under each preset (``paper`` was the default before presets existed;
``auto`` resolves to ``cpu`` on a machine without CUDA). "total" includes building the envs
and the model; "s/update" is the total over the number of PPO updates (rollout + learning).
Prints one table; ``--baseline`` adds the ratio to a saved JSON.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path


def bench(task: str, preset: str, envs: int, steps: int) -> dict:
    from sonogym.agents.configs import resolve_train_config
    from sonogym.agents.train import run_training

    cfg = resolve_train_config(task, "ppo", preset=preset, envs=envs, steps=steps)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        run_training(cfg, Path(d) / "run", progress=False, log=lambda m: None)
        total = time.perf_counter() - t0
    updates = steps // cfg.params.rollouts
    return {
        "task": task,
        "preset": cfg.preset,
        "envs": envs,
        "steps": steps,
        "net": cfg.rl.net,
        "obs_downsample": cfg.rl.obs_downsample,
        "threads": cfg.threads,
        "total s": total,
        "s/update": total / max(1, updates),
        "updates": updates,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["paper", "cpu"])
    ap.add_argument("--task", default="navigation")
    ap.add_argument("--envs", type=int, default=4)
    ap.add_argument("--steps", type=int, default=256)
    ap.add_argument("--json", type=Path, default=None, help="save the rows here")
    ap.add_argument("--baseline", type=Path, default=None, help="a saved --json to compare with")
    args = ap.parse_args()
    rows = [bench(args.task, p, args.envs, args.steps) for p in args.presets]
    base = {}
    if args.baseline:
        base = {r["preset"]: r for r in json.loads(args.baseline.read_text())}
    print(f"{args.task} PPO, {args.envs} envs x {args.steps} steps")
    print("| preset | net | obs_downsample | threads | total s | s/update | vs baseline |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        b = base.get(r["preset"])
        ratio = f"{b['total s'] / r['total s']:.2f}x faster" if b else "-"
        print(f"| {r['preset']} | {r['net']} | {r['obs_downsample']} | {r['threads']} | "
              f"{r['total s']:.1f} | {r['s/update']:.2f} | {ratio} |")  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
