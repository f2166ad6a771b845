"""Frame-to-frame consistency: correlation of images 0.5 mm of probe motion apart.

The paper's limitation: its GAN images lack consistency between consecutive frames. For --poses
random navigation poses around L4 on the seed-0 phantom (1 mm), the 200 x 150 env image at the pose
and at the pose moved by --step (0.5 mm) along the probe's lateral axis x_U (in plane) and along its
elevation axis y_U (out of plane); Pearson correlation of each pair, mean +- sd over poses, for the
model-based ultrasound models and each shipped net (the envs' simulator: LUT fitted once by
``sonogym.ultrasound.learned.matching.matching_sample``).

    python benchmarks/frame_consistency.py [--poses 64] [--step 0.5]
"""

from __future__ import annotations

import argparse
import time

import torch

from sonogym.anatomy import PhantomParams, load_phantom
from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer
from sonogym.ultrasound.learned.matching import matching_sample
from sonogym.ultrasound.learned.shipped import NUM_SHIPPED, shipped_weights
from sonogym.ultrasound.learned.simulator import LearnedSimulator


def pearson(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-image Pearson correlation of (N, ...) tensors."""
    a = a.flatten(1).double()
    b = b.flatten(1).double()
    a = a - a.mean(1, keepdim=True)
    b = b - b.mean(1, keepdim=True)
    return (a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1)).clamp_min(1e-12)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=64)
    ap.add_argument("--step", type=float, default=0.5, help="probe motion, mm")
    ap.add_argument("--seed", type=int, default=0, help="phantom seed")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    t0 = time.time()
    patient = load_phantom(a.seed, PhantomParams(spacing=1e-3))
    slicer = Slicer([patient], ProbeGeometry.linear_2d())
    c = patient.landmarks.vertebra("L4").centre
    g = torch.Generator().manual_seed(1)
    u = torch.rand(a.poses, 3, generator=g, dtype=torch.float64)
    pos, rot = patient.skin.surface_pose(
        c[0] + (u[:, 0] - 0.5) * 0.13, c[2] + (u[:, 1] - 0.5) * 0.13, 1.5 + 2.0 * u[:, 2]
    )
    pos, rot = pos.float(), rot.float()
    d = a.step * 1e-3
    base = slicer(pos, rot)
    moved = {
        "lateral x_U": slicer(pos + d * rot[:, :, 0], rot),
        "elevation y_U": slicer(pos + d * rot[:, :, 1], rot),
    }
    sims = {
        "physical": ModelBasedSimulator("physical"),
        "reference": ModelBasedSimulator("reference"),
    }
    sample = matching_sample([patient], torch.device("cpu"))
    for k in range(NUM_SHIPPED):
        sim = LearnedSimulator(shipped_weights(k))
        sim.fit_source(sample)
        sims[f"learned net {k}"] = sim
    print(f"frame-to-frame Pearson correlation, {a.step} mm probe motion, {a.poses} poses "
          f"around L4, phantom {a.seed}, 200 x 150 images (mean +- sd)")  # fmt: skip
    print(f"{'simulator':15} " + " ".join(f"{k:>16}" for k in moved))
    for name, sim in sims.items():
        img0 = sim.simulate(base)
        cells = []
        for s in moved.values():
            r = pearson(img0, sim.simulate(s))
            cells.append(f"{r.mean():.3f} +- {r.std():.3f}")
        print(f"{name:15} " + " ".join(f"{v:>16}" for v in cells))
    cts = [pearson(base.ct, s.ct) for s in moved.values()]
    print(
        f"{'CT (input)':15} " + " ".join(f"{r.mean():.3f} +- {r.std():.3f}".rjust(16) for r in cts)
    )
    print(f"{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
