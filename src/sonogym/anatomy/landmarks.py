"""Vertebra frames and planned pedicle-screw trajectories, computed from the vertebra masks.

One code path for phantoms and real TotalSegmentator data. Rules (ultrasound_physics.md §4-5):

* Vertebra frame: origin at the vertebral-body centroid; s (superior) along the spine, from the
  neighbouring vertebrae's centroids; a (anterior) from the spinal-canal centre toward the body
  centroid (so axial rotation is captured); l = a x s (toward the patient's right).
* Spinal canal: the hole enclosed by the vertebral ring in a +/-6 mm slab around the centroid.
* Pedicle centre: centroid of the vertebra's voxels lateral to the canal, within the canal's
  middle half in the anterior direction (the bony bridge between body and posterior arch).
* Trajectory: through the pedicle centre, medially converging by 5 deg per lumbar level
  (L4: 20 deg, Dickman 1992), parallel to the superior endplate (no sagittal angle). Entry: where
  the line leaves the bone posteriorly (the posterior bone surface). Target: 80 % of the in-bone
  length from the entry toward the anterior cortex (inside the body). Radius: the largest
  corridor (<= 3.5 mm, 0.25 mm steps) that stays in the vertebra from 5 mm past the entry
  (the entry itself lies on an oblique surface) to the target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from sonogym.anatomy import labels as L
from sonogym.anatomy.volume import Volume

_SPINE_ORDER = ["T11", "T12", "L1", "L2", "L3", "L4", "L5", "S1"]
_MAX_RADIUS = 0.0035  # m, a 7 mm screw
_TARGET_FRACTION = 0.8
_CORRIDOR_START = 0.005  # m past the entry


class LandmarkError(ValueError):
    """A landmark cannot be computed (e.g. the vertebra is absent); the message says why."""


@dataclass(frozen=True)
class VertebraFrame:
    """Centre (3,) metres and rotation (3, 3) (columns l, a, s) of one vertebra in {P}."""

    level: str
    centre: np.ndarray
    rotation: np.ndarray
    canal_centre: np.ndarray
    canal_half_width: float  # m
    canal_half_depth: float  # m

    @property
    def lateral(self) -> np.ndarray:
        return self.rotation[:, 0]

    @property
    def anterior(self) -> np.ndarray:
        return self.rotation[:, 1]

    @property
    def superior(self) -> np.ndarray:
        return self.rotation[:, 2]


@dataclass(frozen=True)
class PedicleTrajectory:
    """A planned pedicle-screw path in {P}: entry on the posterior bone surface, target in the
    body, corridor radius (all metres)."""

    level: str
    side: str  # "left" or "right" (the patient's)
    entry: np.ndarray
    target: np.ndarray
    radius: float
    pedicle_centre: np.ndarray
    pedicle_width: float  # m, lateral extent of the pedicle at its centre

    @property
    def direction(self) -> np.ndarray:
        """Unit vector from entry to target."""
        d = self.target - self.entry
        return d / np.linalg.norm(d)

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.target - self.entry))


@dataclass(frozen=True)
class Landmarks:
    """Frames of the lumbar vertebrae present and planned trajectories for L1-L5, both sides."""

    vertebrae: dict[str, VertebraFrame]
    trajectories: dict[tuple[str, str], PedicleTrajectory]

    def vertebra(self, level: str) -> VertebraFrame:
        if level not in self.vertebrae:
            raise LandmarkError(
                f"vertebra {level} is not in this patient (present: {sorted(self.vertebrae)}); "
                "choose a target vertebra the label map contains"
            )
        return self.vertebrae[level]

    def trajectory(self, level: str = "L4", side: str = "right") -> PedicleTrajectory:
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        self.vertebra(level)
        if (level, side) not in self.trajectories:
            raise LandmarkError(f"no planned trajectory for {level} {side}: see the vertebra mask")
        return self.trajectories[(level, side)]

    @classmethod
    def from_patient(cls, patient: Volume) -> Landmarks:
        labels = patient.labels
        present = [lv for lv in _SPINE_ORDER if (labels == L.VERTEBRA_IDS[lv]).any()]
        if not any(lv in L.LUMBAR_VERTEBRAE for lv in present):
            raise LandmarkError(f"{patient.name}: no lumbar vertebra (L1-L5) in the label map")
        sp, org = patient.spacing, patient.origin
        pts = {}
        for lv in present:
            idx = torch.nonzero(labels == L.VERTEBRA_IDS[lv]).numpy()
            pts[lv] = org + idx * sp
        cents = {lv: p.mean(0) for lv, p in pts.items()}
        vol = _BoneLookup(patient)
        frames: dict[str, VertebraFrame] = {}
        trajs: dict[tuple[str, str], PedicleTrajectory] = {}
        for i, lv in enumerate(present):
            if lv not in L.LUMBAR_VERTEBRAE:
                continue
            up = present[i - 1] if i > 0 else None
            lo = present[i + 1] if i + 1 < len(present) else None
            a_, b_ = cents[up] if up else cents[lv], cents[lo] if lo else cents[lv]
            s_ax = a_ - b_ if up or lo else np.array([0.0, 0.0, 1.0])
            s_ax = s_ax / np.linalg.norm(s_ax)
            frame = _vertebra_frame(lv, pts[lv], cents[lv], s_ax, sp.min())
            frames[lv] = frame
            for side in ("left", "right"):
                t = _plan(lv, side, frame, pts[lv], vol, L.VERTEBRA_IDS[lv], sp.min())
                if t is not None:
                    trajs[(lv, side)] = t
        return cls(frames, trajs)


# ----------------------------------------------------------------------------- internals


class _BoneLookup:
    """Nearest-voxel label lookups at patient-frame points."""

    def __init__(self, patient: Volume) -> None:
        self.labels = patient.labels.numpy()
        self.to_voxel = patient.world_to_voxel_np

    def label_at(self, p: np.ndarray) -> np.ndarray:
        ijk = np.rint(self.to_voxel(p)).astype(int)
        inside = ((ijk >= 0) & (ijk < self.labels.shape)).all(-1)
        ijk = np.clip(ijk, 0, np.array(self.labels.shape) - 1)
        out = self.labels[ijk[..., 0], ijk[..., 1], ijk[..., 2]]
        return np.where(inside, out, 0)


def _project(pts: np.ndarray, origin: np.ndarray, axes: np.ndarray) -> np.ndarray:
    return (pts - origin) @ axes


def _canal(pts, centre, l_ax, a_ax, s_ax, h):
    """Canal centre (3,), half-width, half-depth from the hole in the vertebral ring."""
    q = _project(pts, centre, np.stack([l_ax, a_ax, s_ax], 1))
    slab = q[np.abs(q[:, 2]) < 0.006]
    if len(slab) < 10:
        return None
    lo = slab[:, :2].min(0) - 2 * h
    ij = np.floor((slab[:, :2] - lo) / h).astype(int)
    grid = np.zeros(ij.max(0) + 2, bool)
    grid[ij[:, 0], ij[:, 1]] = True
    grid = ndimage.binary_closing(grid, iterations=1)
    hole = ndimage.binary_fill_holes(grid) & ~grid
    lab, n = ndimage.label(hole)
    if n == 0:
        return None
    sizes = ndimage.sum(hole, lab, range(1, n + 1))
    k = int(np.argmax(sizes)) + 1
    cells = np.argwhere(lab == k)
    if len(cells) * h * h < 30e-6:  # < 30 mm^2: not a canal
        return None
    uv = lo + (cells + 0.5) * h
    c = uv.mean(0)
    half_w = (uv[:, 0].max() - uv[:, 0].min() + h) / 2
    half_d = (uv[:, 1].max() - uv[:, 1].min() + h) / 2
    return centre + c[0] * l_ax + c[1] * a_ax, half_w, half_d


def _vertebra_frame(level, pts, centroid, s_ax, h) -> VertebraFrame:
    a0 = np.array([0.0, 1.0, 0.0]) - s_ax[1] * s_ax
    a0 /= np.linalg.norm(a0)
    l0 = np.cross(a0, s_ax)
    canal = _canal(pts, centroid, l0, a0, s_ax, h)
    if canal is None:
        raise LandmarkError(
            f"vertebra {level}: its mask has no closed vertebral ring around a spinal canal"
        )
    cc, hw, hd = canal
    # Body: voxels anterior of the canal, within 30 mm of the midline.
    q = _project(pts, cc, np.stack([l0, a0, s_ax], 1))
    body = pts[(q[:, 1] > hd + 0.002) & (np.abs(q[:, 0]) < 0.03)]
    body_c = body.mean(0)
    a_ax = body_c - cc
    a_ax -= (a_ax @ s_ax) * s_ax
    a_ax /= np.linalg.norm(a_ax)
    l_ax = np.cross(a_ax, s_ax)
    # Re-measure the canal in the refined frame.
    canal = _canal(pts, centroid, l_ax, a_ax, s_ax, h)
    if canal is not None:
        cc, hw, hd = canal
    rot = np.stack([l_ax, a_ax, s_ax], 1)
    return VertebraFrame(level, body_c, rot, cc, float(hw), float(hd))


def _march(vol, start, direction, label, step, max_len, max_gap):
    """Distance along ``direction`` from ``start`` to where the bone of ``label`` ends (gaps up
    to ``max_gap`` are bridged)."""
    n = int(max_len / step)
    ts = np.arange(n) * step
    inside = vol.label_at(start + ts[:, None] * direction) == label
    last, gap = 0.0, 0.0
    for t, ok in zip(ts, inside, strict=True):
        if ok:
            last, gap = t, 0.0
        else:
            gap += step
            if gap > max_gap:
                break
    return last


def _plan(level, side, frame, pts, vol, label, h) -> PedicleTrajectory | None:
    sgn = 1.0 if side == "right" else -1.0
    q = _project(pts, frame.canal_centre, frame.rotation)
    sel = (
        (np.abs(q[:, 1]) < 0.5 * frame.canal_half_depth)
        & (sgn * q[:, 0] > frame.canal_half_width)
        & (sgn * q[:, 0] < frame.canal_half_width + 0.015)
    )
    if sel.sum() < 3:
        return None
    ped = pts[sel]
    pc = ped.mean(0)
    n_level = int(level[1])
    th = math.radians(5.0 * n_level)
    d = math.cos(th) * frame.anterior - sgn * math.sin(th) * frame.lateral
    d /= np.linalg.norm(d)
    # Width across the pedicle axis, in the cross-section through the pedicle centre.
    perp = np.cross(frame.superior, d)
    rel = ped - pc
    near = (np.abs(rel @ d) < h) & (np.abs(rel @ frame.superior) < h)
    width = float(np.ptp(rel[near] @ perp) + h) if near.sum() > 1 else float("nan")
    step = h / 4
    back = _march(vol, pc, -d, label, step, 0.08, 1.01 * h)
    entry = pc - back * d
    fwd = _march(vol, entry, d, label, step, 0.12, 2.01 * h)
    target = entry + _TARGET_FRACTION * fwd * d
    radius = _corridor_radius(vol, entry, target, label, h)
    return PedicleTrajectory(level, side, entry, target, radius, pc, width)


def _corridor_radius(vol, entry, target, label, h) -> float:
    axis = target - entry
    length = np.linalg.norm(axis)
    d = axis / length
    e1 = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(d, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    # The corridor is checked from _CORRIDOR_START past the entry: the entry itself lies on an
    # oblique bone surface, which any ring around the axis crosses.
    ts = np.arange(min(_CORRIDOR_START, length / 2), length, h / 2)[:, None, None]
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = np.cos(ang)[None, :, None] * e1 + np.sin(ang)[None, :, None] * e2
    best = 0.0
    for r in np.arange(0.00025, _MAX_RADIUS + 1e-9, 0.00025):
        p = entry + ts * d + r * ring
        ok = vol.label_at(p) == label
        if not ok.all():
            break
        best = r
    return round(float(best), 6)
