"""Morphometry of the lumbar spine and its soft-tissue cover, measured the same way on any patient.

The same code measures procedural phantoms and real TotalSegmentator subjects, so the two can be
compared number by number (``sonogym morphometry``, docs/anatomy.md). Everything is computed from
the label map, the skin surface and the vertebra frames of ``patient.landmarks``.

Frames and units. The patient frame {P} is RAS in metres, the patient prone: the back is the
smallest-y body surface. A vertebra's frame (``VertebraFrame``) has its origin at the body
centroid and axes l (toward the patient's right), a (anterior, from the canal centre toward the
body) and s (superior, along the spine). "Behind the canal centre" means a smaller a than the
canal centre's. Every reported value is in millimetres.

Per lumbar level (L1-L5), in the level's own frame unless said otherwise:

* ``tip_depth``: skin to spinous tip. The spinous tip is the level's voxel with the smallest a
  (the most posterior). Its depth is its distance to the nearest point of the back's skin
  surface (``SkinSurface`` height map, searched within 60 mm).
* ``lamina_depth``: skin to lamina. The paramedian bands are |l - l_c| = 0.8 canal half-widths
  +- 1.5 mm (l_c the canal centre's l): over the canal's lateral part, on the laminae, clear of
  the spinous process and of the articular processes. For each side, the level's voxel in the
  band behind the canal centre with the smallest a; its skin distance as above; the mean of both
  sides.
* ``interlaminar_window``: height of the interlaminar window below the level, in the paramedian
  bands: the lowest s of this level's voxels behind its canal centre minus the highest s of the
  next bone below (L5 for L4, S1 or the sacrum for L5) behind the same canal centre, minus one
  voxel, both in this level's frame; the mean of both sides. Negative when the laminae overlap.
* ``tp_span``: transverse-process span, tip to tip: the l-extent of the level's voxels plus one
  voxel.
* ``facet_width``: distance between the left and right facet joints below the level. A joint's
  contact zone is the set of this level's voxels behind its canal centre, more than 0.7 canal
  half-widths from the midline on that side, that lie within ``FACET_CONTACT`` (4 mm) of the next
  bone below; the l-distance between the two zones' centroids. NaN if a side has no contact.
* ``body_width``: l-extent (plus one voxel) of the body at mid-height: voxels with |s| < 2 mm and
  a > 3 mm (the body's front part, clear of the pedicles and of L5's transverse processes, which
  join the body's sides).
* ``body_depth``: a-extent (plus one voxel) of the level's voxels in the midline band |l| < 3 mm,
  |s| < 2 mm, in front of the canal centre: posterior wall to anterior cortex.

At the L4 goal views (the probe pose on the skin above the L4 body centroid, beam along the
skin's inward normal; transverse: yaw pi, sagittal: yaw pi/2; ``SkinSurface.surface_pose``):

* ``bone_profile``: the first-bone-hit depth across the probe's width. For each lateral offset u
  of ``PROFILE_OFFSETS`` along the image's lateral axis x_U, the depth along the beam z_U of the
  beam's first sample (every 0.25 mm, nearest voxel) whose label is a bone
  (``labels.BONE_IDS``), or ``PROFILE_DEPTH`` (the image's 100 mm) when it meets no bone within
  the image.
* ``muscle_profile`` (transverse view only): the skin-to-paraspinal-muscle depth across the
  probe's width, the same beams: the depth of the first sample labelled ``autochthon_left`` or
  ``autochthon_right`` before any bone, or ``PROFILE_DEPTH`` when bone (or nothing) comes first.
  It shows the muscles' convex backs and the fat-filled cleft between them over the spinous
  tip, the arches a transverse image shows above the bone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from sonogym.anatomy import labels as L
from sonogym.anatomy.landmarks import VertebraFrame
from sonogym.anatomy.volume import Volume

LEVELS = ("L1", "L2", "L3", "L4", "L5")
#: Per-level measurements, in table order.
LEVEL_MEASURES = (
    "tip_depth",
    "lamina_depth",
    "interlaminar_window",
    "tp_span",
    "facet_width",
    "body_width",
    "body_depth",
)
#: Goal views: name -> yaw (rad) of the probe's lateral axis in the frontal plane.
GOAL_VIEWS = {"transverse": math.pi, "sagittal": math.pi / 2}
#: Name of the skin-to-muscle profile at the transverse goal view (a ``profiles`` key).
MUSCLE_VIEW = "muscle"
#: Label ids of the paraspinal muscles (TotalSegmentator ``autochthon_left/right``).
PARASPINAL_IDS = (86, 87)
#: Lateral offsets (mm) along the image's lateral axis of the reported bone-hit profile.
PROFILE_OFFSETS = tuple(float(u) for u in range(-35, 36, 5))
#: Depth (mm) of the image: a beam meeting no bone within it reads this depth.
PROFILE_DEPTH = 100.0
#: Paramedian bands: this share of the canal half-width from the canal centre, +- _BAND mm.
PARAMEDIAN = 0.8
_BAND = 1.5
#: Distance (mm) within which two neighbouring levels' voxels count as a facet contact.
FACET_CONTACT = 4.0
_SKIN_SEARCH = 60.0  # mm, radius searched on the skin height map for the nearest skin point
_STEP = 0.25  # mm, sampling step along a beam


@dataclass(frozen=True)
class Morphometry:
    """One patient's measurements (mm): ``levels[level][measure]`` and
    ``profiles[view]`` = depths at ``PROFILE_OFFSETS``."""

    name: str
    levels: dict[str, dict[str, float]]
    profiles: dict[str, tuple[float, ...]]

    def flat(self) -> dict[str, float]:
        """Every value under one key: ``"L4 tip_depth"``, ``"transverse +5"``."""
        out = {f"{lv} {m}": v for lv, row in self.levels.items() for m, v in row.items()}
        for view, prof in self.profiles.items():
            out.update({f"{view} {u:+.0f}": d for u, d in zip(PROFILE_OFFSETS, prof, strict=True)})
        return out


def measure(patient, levels: tuple[str, ...] = LEVELS) -> Morphometry:
    """Measure ``patient`` (a ``Patient``: volumes, skin and landmarks) as the module docstring
    defines."""
    lab = patient.labels.numpy()
    lm = patient.landmarks
    pts = _level_points(patient, lab)
    rows = {}
    for i, lv in enumerate(levels):
        frame = lm.vertebra(lv)
        below = _BELOW.get(lv)
        lower = pts.get(below) if below else None
        if lv == "L5":  # S1 and the sacrum (TotalSegmentator v1 has no S1 class)
            parts = [pts[k] for k in ("S1", "sacrum") if k in pts]
            lower = np.concatenate(parts) if parts else None
        rows[lv] = _measure_level(patient, frame, pts[lv], lower)
        del i
    profiles = {}
    f4 = lm.vertebra("L4")
    for view, yaw in GOAL_VIEWS.items():
        profiles[view] = tuple(float(d) for d in bone_profile(patient, f4, yaw))
    profiles[MUSCLE_VIEW] = tuple(float(d) for d in muscle_profile(patient, f4))
    return Morphometry(patient.name, rows, profiles)


_BELOW = {"L1": "L2", "L2": "L3", "L3": "L4", "L4": "L5"}


def _level_points(patient: Volume, lab: np.ndarray) -> dict[str, np.ndarray]:
    """Patient-frame points (m) of every spine level's voxels, plus "S1" and "sacrum"."""
    ids = {lv: L.VERTEBRA_IDS[lv] for lv in (*LEVELS, "S1")}
    ids["sacrum"] = L.LABEL_IDS["sacrum"]
    out = {}
    for name, i in ids.items():
        idx = np.argwhere(lab == i)
        if len(idx):
            out[name] = patient.origin + idx * patient.spacing
    return out


def _in_frame(pts: np.ndarray, frame: VertebraFrame) -> np.ndarray:
    """(N, 3) points (m) -> (N, 3) (l, a, s) in mm."""
    return (pts - frame.centre) @ frame.rotation * 1e3


def _measure_level(patient, frame: VertebraFrame, pts, lower) -> dict[str, float]:
    h = float(patient.spacing.min()) * 1e3
    q = _in_frame(pts, frame)
    cc = _in_frame(frame.canal_centre[None], frame)[0]
    cw = frame.canal_half_width * 1e3
    behind = q[:, 1] < cc[1]
    out = {}
    tip = pts[np.argmin(q[:, 1])]
    out["tip_depth"] = skin_distance(patient, tip[None])[0]
    lam, win = [], []
    ql = _in_frame(lower, frame) if lower is not None else None
    for sgn in (-1.0, 1.0):
        l0 = cc[0] + sgn * PARAMEDIAN * cw
        band = behind & (np.abs(q[:, 0] - l0) <= _BAND)
        if not band.any():
            continue
        lam.append(pts[band][np.argmin(q[band, 1])])
        if ql is not None:
            lo = (ql[:, 1] < cc[1]) & (np.abs(ql[:, 0] - l0) <= _BAND)
            if lo.any():
                win.append(q[band, 2].min() - ql[lo, 2].max() - h)
    out["lamina_depth"] = float(np.mean(skin_distance(patient, np.array(lam)))) if lam else math.nan
    out["interlaminar_window"] = float(np.mean(win)) if win else math.nan
    out["tp_span"] = float(np.ptp(q[:, 0]) + h)
    out["facet_width"] = _facet_width(patient, q, lower, frame, cc, cw, behind)
    mid = np.abs(q[:, 2]) < 2.0
    body = mid & (q[:, 1] > 3.0)
    out["body_width"] = float(np.ptp(q[body, 0]) + h) if body.any() else math.nan
    core = mid & (np.abs(q[:, 0] - cc[0]) < 3.0) & (q[:, 1] > cc[1])
    out["body_depth"] = float(np.ptp(q[core, 1]) + h) if core.any() else math.nan
    return out


def _facet_width(patient, q, lower, frame, cc, cw, behind) -> float:
    """l-distance between the left and right contact zones with the bone below (module doc)."""
    if lower is None:
        return math.nan
    sp = patient.spacing
    pts = frame.centre + (q * 1e-3) @ frame.rotation.T
    # Distance to the lower bone on a crop around this level (voxel grid of the patient).
    lo_idx = np.rint((lower - patient.origin) / sp).astype(int)
    up_idx = np.rint((pts - patient.origin) / sp).astype(int)
    pad = int(math.ceil(FACET_CONTACT * 1e-3 / sp.min())) + 2
    a = np.minimum(up_idx.min(0), lo_idx.min(0)) - pad
    b = np.maximum(up_idx.max(0), lo_idx.max(0)) + pad + 1
    grid = np.ones(b - a, bool)
    k = lo_idx - a
    grid[k[:, 0], k[:, 1], k[:, 2]] = False
    dist = ndimage.distance_transform_edt(grid, sampling=sp * 1e3)
    k = up_idx - a
    near = dist[k[:, 0], k[:, 1], k[:, 2]] <= FACET_CONTACT
    zones = []
    for sgn in (-1.0, 1.0):
        z = near & behind & (sgn * (q[:, 0] - cc[0]) > 0.7 * cw)
        if not z.any():
            return math.nan
        zones.append(q[z, 0].mean())
    return float(zones[1] - zones[0])


def skin_distance(patient, pts: np.ndarray) -> np.ndarray:
    """(N,) distance (mm) from points (N, 3) in metres to the nearest point of the back's skin
    surface, searched on the height map within 60 mm of each point's (x, z)."""
    pts = np.asarray(pts, np.float64).reshape(-1, 3)
    g = np.arange(-_SKIN_SEARCH, _SKIN_SEARCH + 1e-9, 1.0) * 1e-3
    gx, gz = np.meshgrid(g, g, indexing="ij")
    out = np.empty(len(pts))
    for i, p in enumerate(pts):
        x = torch.tensor(p[0] + gx)
        z = torch.tensor(p[2] + gz)
        y = patient.skin.height(x, z).numpy()
        d2 = (x.numpy() - p[0]) ** 2 + (y - p[1]) ** 2 + (z.numpy() - p[2]) ** 2
        out[i] = math.sqrt(d2.min()) * 1e3
    return out


def bone_profile(patient, frame: VertebraFrame, yaw: float) -> np.ndarray:
    """(len(PROFILE_OFFSETS),) first-bone-hit depths (mm) of the view above ``frame``'s body
    centroid with ``yaw`` (module docstring)."""
    return bone_hit_depths(patient, frame.centre[0], frame.centre[2], yaw, PROFILE_OFFSETS)


def muscle_profile(patient, frame: VertebraFrame, offsets=PROFILE_OFFSETS) -> np.ndarray:
    """(len(offsets),) skin-to-paraspinal-muscle depths (mm) of the transverse view above
    ``frame``'s body centroid at lateral ``offsets`` (mm) (module docstring)."""
    lab, ok = _beam_labels(
        patient, frame.centre[0], frame.centre[2], GOAL_VIEWS["transverse"], offsets,
        PROFILE_DEPTH,
    )  # fmt: skip
    before_bone = np.cumsum(_is_bone(lab) & ok, 1) == 0
    return _first_depth(np.isin(lab, PARASPINAL_IDS) & ok & before_bone, PROFILE_DEPTH)


def bone_hit_depths(
    patient,
    x: float,
    z: float,
    yaw: float,
    offsets,
    max_depth: float = PROFILE_DEPTH,
) -> np.ndarray:
    """First-bone-hit depth (mm) along the beam for lateral ``offsets`` (mm) of the probe pose on
    the skin at (x, z) (m) with ``yaw`` (rad) and no tilt; ``max_depth`` where no bone is met."""
    lab, ok = _beam_labels(patient, x, z, yaw, offsets, max_depth)
    return _first_depth(_is_bone(lab) & ok, max_depth)


def first_bone_labels(
    patient,
    x: float,
    z: float,
    yaw: float,
    offsets,
    max_depth: float = PROFILE_DEPTH,
) -> np.ndarray:
    """(len(offsets),) label id of the first bone each beam of ``bone_hit_depths`` meets (which
    vertebra a view shows at each lateral offset), 0 where it meets none within ``max_depth``."""
    lab, ok = _beam_labels(patient, x, z, yaw, offsets, max_depth)
    hit = _is_bone(lab) & ok
    first = lab[np.arange(len(lab)), hit.argmax(1)]
    return np.where(hit.any(1), first, 0).astype(np.int64)


def _is_bone(lab: np.ndarray) -> np.ndarray:
    return np.isin(lab, np.fromiter(L.BONE_IDS, np.uint8))


def _first_depth(hit: np.ndarray, max_depth: float) -> np.ndarray:
    """Per beam (rows of ``hit``, samples every ``_STEP`` mm), the depth (mm) of its first hit,
    ``max_depth`` where it has none."""
    return np.where(hit.any(1), hit.argmax(1) * _STEP, max_depth).astype(np.float64)


def _beam_labels(patient, x, z, yaw, offsets, max_depth) -> tuple[np.ndarray, np.ndarray]:
    """(U, D) labels of the beams of the probe pose on the skin at (x, z) with ``yaw``, sampled
    every ``_STEP`` mm to ``max_depth`` (nearest voxel), and whether each sample is in the
    volume."""
    pos, rot = patient.skin.surface_pose(
        torch.tensor([float(x)], dtype=torch.float64),
        torch.tensor([float(z)], dtype=torch.float64),
        torch.tensor([float(yaw)], dtype=torch.float64),
    )
    pos, rot = pos[0].numpy(), rot[0].numpy()
    u = np.asarray(offsets, np.float64)[:, None, None] * 1e-3
    d = np.arange(0.0, max_depth + 1e-9, _STEP)[None, :, None] * 1e-3
    ray = pos + u * rot[:, 0] + d * rot[:, 2]  # (U, D, 3)
    ijk = np.rint((ray - patient.origin) / patient.spacing).astype(np.int64)
    shape = np.array(patient.shape)
    ok = ((ijk >= 0) & (ijk < shape)).all(-1)
    ijk = np.clip(ijk, 0, shape - 1)
    return patient.labels.numpy()[ijk[..., 0], ijk[..., 1], ijk[..., 2]], ok
