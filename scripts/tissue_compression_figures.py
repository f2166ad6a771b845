"""Pictures of one view with the probe pressed at several forces (docs/ultrasound.md,
"Tissue compression under the probe").

    PYTHONPATH=src python scripts/tissue_compression_figures.py [--out docs] [--forces 0 2 10 20]

The view is navigation's goal {G} on the seed-0 phantom at 1 mm: the transverse image over L4
whose beam passes through the vertebral body's centroid. For each force it writes
``tissue-compression-<F>N.png``: the ``physical`` ultrasound image beside the label image, both
warped by the same compression, with the static view's first bone row per column as a dashed
line; and prints the compression of the beam under the image's centre.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

from sonogym.anatomy import load_phantom
from sonogym.anatomy.labels import BONE_IDS
from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer
from sonogym.ultrasound.compression import TissueCompression, probe_footprint


def first_bone_rows(labels: torch.Tensor) -> np.ndarray:
    """(W,) the first bone row of each column of an (H, W) label image (nan: none)."""
    lut = torch.zeros(256, dtype=torch.bool)
    lut[sorted(BONE_IDS)] = True
    bone = lut[labels.long()]
    rows = bone.float().argmax(0).double().numpy()
    rows[~bone.any(0).numpy()] = np.nan
    return rows


def figure(us, labels, static_bone, force, compression_mm, probe, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = us.shape
    extent = (-w * probe.width_spacing * 500, w * probe.width_spacing * 500,
              h * probe.depth_spacing * 1e3, 0)  # fmt: skip
    x = (np.arange(w) - (w - 1) / 2) * probe.width_spacing * 1e3
    fig, axes = plt.subplots(1, 2, figsize=(6.4, 4.0))
    axes[0].imshow(us, cmap="gray", vmin=0, vmax=1, extent=extent)
    axes[1].imshow(labels.astype(np.float32), cmap="tab20", vmin=0, vmax=122,
                   interpolation="nearest", extent=extent)  # fmt: skip
    for ax, title in zip(axes, ("ultrasound (physical)", "labels"), strict=True):
        ax.plot(x, (static_bone + 0.5) * probe.depth_spacing * 1e3, "--", color="yellow", lw=0.8)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("lateral (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("depth (mm)", fontsize=8)
    fig.suptitle(
        f"{force:g} N: {compression_mm:.1f} mm of compression under the centre "
        "(dashed: bone at 0 N)",
        fontsize=9,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("docs"))
    ap.add_argument("--forces", type=float, nargs="+", default=[2.0, 10.0, 20.0])
    args = ap.parse_args()
    patient = load_phantom(0)
    probe = ProbeGeometry.linear_2d()
    slicer = Slicer(patient, probe)
    model = TissueCompression(probe, slicer.block)
    # the beam under the image's centre alone, as the envs' info["compression_mm"] reads it
    beam = ProbeGeometry(probe.depth_px, 1, 1, probe.depth_spacing, probe.width_spacing)
    beam_slicer = slicer.sharing(beam, (slicer.block[0], 1))
    beam_model = TissueCompression(beam, beam_slicer.block, probe_footprint(probe), stride=(1, 1))
    sim = ModelBasedSimulator("physical")
    centre = torch.tensor(patient.landmarks.vertebra("L4").centre[None])
    x, z = patient.skin.aim(centre, torch.tensor([0]))
    pos, rot = patient.skin.surface_pose(x, z, torch.full_like(x, math.pi))
    static_bone = first_bone_rows(slicer(pos, rot).labels[0, 0])
    print("| force (N) | compression under the centre (mm) | bone rise, median of columns (mm) |")
    print("|---|---|---|")
    for force in args.forces:
        s = slicer(pos, rot, warp=model.bind(torch.tensor([force])))
        us = sim.simulate(s)[0, 0].numpy()
        centre = beam_model.bind(torch.tensor([force]))
        beam_slicer(pos, rot, warp=centre)
        mm = float(centre.centre[0]) * 1e3
        rise = np.nanmedian(static_bone - first_bone_rows(s.labels[0, 0])) * probe.depth_spacing
        print(f"| {force:g} | {mm:.2f} | {rise * 1e3:.2f} |")
        path = args.out / f"tissue-compression-{force:g}N.png"
        figure(us, s.labels[0, 0].numpy(), static_bone, force, mm, probe, path)


if __name__ == "__main__":
    main()
