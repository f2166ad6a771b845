"""The shared real subject's spine masks for the landmark tests: the crop to L1-S1, resampling
and per-vertebra degradations, landmarks from a label array alone.

A module of its own, not conftest.py: several test folders have a conftest, and a plain
``from conftest import`` resolves to whichever was imported first."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from sonogym.anatomy import Landmarks, Patient, load_totalsegmentator
from sonogym.anatomy import labels as L

SUBJECT = Path(__file__).resolve().parents[1] / "data" / "totalsegmentator_example"
LEVELS = ("L1", "L2", "L3", "L4", "L5")
SPINE = ("vertebrae_T12", *(f"vertebrae_{lv}" for lv in LEVELS), "sacrum")
VIDS = [L.LABEL_IDS[n] for n in SPINE]


def spine_crop(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """(labels, affine): the subject's spine masks at 3 mm, cropped to L1-S1 (+4 voxels);
    ``folder`` (new) receives a subject folder of links to the files read."""
    (folder / "segmentations").mkdir(parents=True)
    (folder / "ct.nii.gz").symlink_to(SUBJECT / "ct.nii.gz")
    for name in SPINE:
        (folder / "segmentations" / f"{name}.nii.gz").symlink_to(
            SUBJECT / "segmentations" / f"{name}.nii.gz"
        )
    p = load_totalsegmentator(folder, spacing=None)
    lab = np.where(np.isin(p.labels.numpy(), VIDS), p.labels.numpy(), 0).astype(np.uint8)
    idx = np.argwhere(np.isin(lab, VIDS[1:]))
    lo, hi = np.maximum(idx.min(0) - 4, 0), np.minimum(idx.max(0) + 5, lab.shape)
    aff = p.affine.copy()
    aff[:3, 3] += lo * p.spacing
    return np.ascontiguousarray(lab[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]), aff


def landmarks_of(lab, aff, name) -> Landmarks:
    ct = torch.zeros(lab.shape)  # the landmarks read the labels only
    return Patient(ct=ct, labels=torch.from_numpy(lab), affine=aff, name=name).landmarks


def axis_errors(f, ref) -> list[float]:
    """Angles (deg) between the l, a and s axes of two vertebra frames."""
    return [
        math.degrees(math.acos(min(1.0, f.rotation[:, k] @ ref.rotation[:, k]))) for k in range(3)
    ]


def resample(lab, aff, h, smooth=False):
    """Labels on a grid of ``h`` over the same field of view (voxel faces aligned with the old
    ones): nearest, or each mask smoothed (sigma half a voxel), interpolated and thresholded."""
    h0, org0 = aff[0, 0], aff[:3, 3]
    n = np.floor(np.array(lab.shape) * h0 / h + 1e-6).astype(int)
    org = org0 - 0.5 * h0 + 0.5 * h
    coords = [(org[a] + h * np.arange(n[a]) - org0[a]) / h0 for a in range(3)]
    if smooth:
        grid = np.meshgrid(*coords, indexing="ij")
        out, best = np.zeros(n, np.uint8), np.full(n, 0.5, np.float32)
        for i in np.unique(lab)[1:]:
            f = ndimage.gaussian_filter((lab == i).astype(np.float32), 0.5)
            v = ndimage.map_coordinates(f, grid, order=1, mode="nearest")
            out[v > best] = i
            best = np.maximum(best, v)
    else:
        idx = [
            np.clip(np.floor(c + 0.5).astype(int), 0, s - 1)
            for c, s in zip(coords, lab.shape, strict=True)
        ]
        out = lab[np.ix_(*idx)]
    new = np.diag([h, h, h, 1.0])
    new[:3, 3] = org
    return out, new


def per_vertebra(lab, fn, where=None):
    """``fn`` applied to each vertebra's mask (restricted to ``where`` (mask) when given)."""
    out = lab.copy()
    for i in VIDS:
        m = lab == i
        if not m.any():
            continue
        new = fn(m)
        if where is not None:
            new = np.where(where, new, m)
        out[m & ~new] = 0
        out[new & (out == 0)] = i
    return out
