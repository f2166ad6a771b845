"""Where a navigation policy's final errors lie, and what removing one part would leave.

    python benchmarks/navigation_errors.py DIR/episodes/*.npz

From ``sonogym eval`` episode logs (the ``policy`` controller's tracked point at the end of each
episode, x across the spine and z along it, mm from {G}): the median |x| and |z|, the share of
level misses (|z| > ``LEVEL_MISS_MM``, the navigation env's ``level_miss`` metric), and the
frontal-plane error's mean, median and share within 10 mm as run and with one part removed:
x = 0 (only the error along the spine left), z = 0 (only the error across it), and level
misses' z set to 0 (those episodes moved to the goal's height, the others as run). A target
that the error across the spine alone already misses cannot be met by better level finding,
and the other way round.
"""

from __future__ import annotations

import argparse

import numpy as np

from sonogym.envs.navigation import LEVEL_MISS_MM as LEVEL_MM
from sonogym.evaluation.episodes import load_log

WITHIN_MM = 10.0


def final_offsets(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(x, z) in mm from {G} of the policy's last tracked point in each episode of a log."""
    log = load_log(path)
    if log.meta.get("task") != "navigation":
        raise SystemExit(f"{path}: a {log.meta.get('task')} log; this reads navigation logs only")
    cols = log.meta["track_columns"]
    end = log.tracks["policy"][:, -1]
    return end[:, cols.index("x")].astype(float), end[:, cols.index("z")].astype(float)


def what_if(x: np.ndarray, z: np.ndarray) -> dict[str, np.ndarray]:
    """Frontal-plane errors (mm) as run and with one part removed (see the module docstring)."""
    level_miss = np.abs(z) > LEVEL_MM
    return {
        "as run": np.hypot(x, z),
        "x = 0 (along the spine only)": np.abs(z),
        "z = 0 (across the spine only)": np.abs(x),
        "level misses at z = 0": np.hypot(x, np.where(level_miss, 0.0, z)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", help="episode logs (.npz) of sonogym eval")
    args = ap.parse_args()
    for path in args.logs:
        x, z = final_offsets(path)
        miss = np.abs(z) > LEVEL_MM
        print(
            f"\n{path}: {len(x)} episodes; |x| median {np.median(np.abs(x)):.1f} mm "
            f"(x median {np.median(x):+.1f}), |z| median {np.median(np.abs(z)):.1f} mm; "
            f"level misses {miss.mean():.0%} (cranial {(z > LEVEL_MM).mean():.0%}, "
            f"caudal {(z < -LEVEL_MM).mean():.0%})\n"
        )
        print("| error | mean [mm] | median [mm] | within 10 mm |")
        print("|---|---:|---:|---:|")
        for name, e in what_if(x, z).items():
            print(
                f"| {name} | {e.mean():.1f} | {np.median(e):.1f} | {(e <= WITHIN_MM).mean():.0%} |"
            )


if __name__ == "__main__":
    main()
