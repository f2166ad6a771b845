"""Preview figure of a patient: CT slices through L4 with label contours and planned
pedicle trajectories (axial, sagittal, coronal)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sonogym.anatomy.patient import Patient


def save_preview(patient: Patient, path: str | Path, level: str = "L4") -> Path:
    """Write a PNG with three orthogonal CT slices through ``level``'s body centre."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    ct, lab = patient.ct.numpy(), patient.labels.numpy()
    lm = patient.landmarks
    frame = lm.vertebra(level)
    ijk = np.rint(patient.world_to_voxel_np(frame.centre)).astype(int)
    ijk = np.clip(ijk, 0, np.array(ct.shape) - 1)
    lo, sp = patient.origin * 1e3, patient.spacing * 1e3
    hi = lo + sp * (np.array(ct.shape) - 1)
    # (name, CT plane, label plane, horizontal axis, vertical axis)
    views = [
        ("axial (from feet)", ct[:, :, ijk[2]], lab[:, :, ijk[2]], 0, 1),
        ("sagittal (from right)", ct[ijk[0], :, :], lab[ijk[0], :, :], 1, 2),
        ("coronal (from back)", ct[:, ijk[1], :], lab[:, ijk[1], :], 0, 2),
    ]
    fig, axes = plt.subplots(1, 3, figsize=(18, 6.5))
    for ax, (title, img, lbl, h, v) in zip(axes, views, strict=True):
        ext = (lo[h], hi[h], lo[v], hi[v])
        ax.imshow(img.T, cmap="gray", vmin=-400, vmax=1400, origin="lower", extent=ext)
        ids = [i for i in np.unique(lbl).tolist() if i]
        cmap = plt.get_cmap("tab20")
        for k, i in enumerate(ids):
            ax.contour(
                (lbl == i).T.astype(float),
                levels=[0.5],
                colors=[cmap(k % 20)],
                linewidths=0.6,
                origin="lower",
                extent=ext,
            )
        for (lv, _side), tr in lm.trajectories.items():
            e, t = tr.entry * 1e3, tr.target * 1e3
            style = "r-" if lv == level else "y-"
            ax.plot([e[h], t[h]], [e[v], t[v]], style, lw=1.5 if lv == level else 0.8)
        ax.set_title(f"{patient.name}: {title} through {level}")
        ax.set_xlabel(f"{'xyz'[h]} (mm)")
        ax.set_ylabel(f"{'xyz'[v]} (mm)")
        if v == 1:
            ax.invert_yaxis()  # posterior (back) at the top: the prone patient seen from the feet
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
