"""Vertebra frames and planned pedicle-screw trajectories, computed from the vertebra masks.

One code path for phantoms and real TotalSegmentator data, ground-truth masks or model output,
at 0.5-3 mm. Rules (docs/anatomy.md):

* Vertebra frame: origin at the vertebral-body centroid (the vertebra's voxels in front of the
  canal's anterior border, within 30 mm of it laterally, cut in the vertebra's own axially
  rotated frame); s (superior) along the spine: first from the neighbouring vertebrae's
  centroids, then from the curve through the body centroids (a central difference between the
  neighbours' bodies, at an end of the spine in view the tangent of the quadratic through three
  bodies), which a rough or damaged posterior arch does not move;
  a (anterior) from the spinal-canal centre toward the body centroid (so axial rotation is
  captured); l = a x s (toward the patient's right).
* Spinal canal, in the axial projection of a +-10 mm slab (then +-5 mm) around the vertebra's
  centroid, the first of:
    1. the empty region the vertebral ring encloses, gaps in the arch (thin laminae, partial
       volume) bridged by closings of radius ``RING_GAP_CLOSING`` (up to 6 mm: 12 mm gaps);
    2. the spinal_canal / spinal_cord label behind the body, when the label map has one;
    3. the empty region behind the body inside the projection's convex hull (an arch open wider
       than the closings bridge).
  A hole counts only behind the vertebra's centroid, within 15 mm of it laterally, at least
  15 mm^2 and 4 mm across both ways. The canal found counts only where its centre lies within
  ``CANAL_MIDLINE_TOLERANCE`` plus one voxel of the vertebra's midsagittal plane, it is at least
  ``CANAL_MIN_WIDTH`` wide and at most ``CANAL_MAX_ASPECT`` times deeper than wide; else it is a
  notch between the processes, or the slit a mask that fills the canal leaves of it.
* Midsagittal plane: the plane through s, within +-``MIRROR_SPAN`` of the patient's anterior,
  about which the vertebra's axial projection best matches its mirror image.
* Frame from the bone, for L1-L5 where the mask shows no canal (a canal the mask fills or
  narrows to a few voxels, and no spinal_canal or spinal_cord label): the body is the anterior
  mass. Along the midsagittal plane's anterior axis, the area of the vertebra's cross-section
  (within 30 mm of the plane) rises to the body's, falls where the body ends and rises again
  over the pedicles and the arch; the body's posterior wall is where it falls below 75 % of the
  largest so far, or halfway down to the trough between body and arch where that trough is
  shallower. The origin is the centroid of the voxels in front of the wall, within 30 mm of the
  plane. The canal is estimated on the plane behind the wall, half as wide as the body and 0.46
  as deep (adult lumbar proportions); a runs from its centre toward the body centroid, as
  above. ``VertebraFrame.canal_source`` is then "bone", and the trajectory planner reads the
  estimated canal (its elliptic cylinder along s) as not bone.
* Refused (``Landmarks.vertebra`` raises a ``LandmarkError`` naming the level and why): a
  vertebra absent from the label map, one touching the field of view's edge (the scan cuts
  it), and one whose mask shows no canal and has no posterior elements behind its body (under
  15 % of its voxels: the mask lacks its posterior arch).
* Pedicle centre: centroid of the vertebra's voxels lateral to the canal, within the canal's
  middle half in the anterior direction (the bony bridge between body and posterior arch).
* Trajectory: the straight path, among those the anatomical rules allow, that keeps the widest
  corridor inside the vertebra (``plan_corridor``):
    - medial convergence 5 deg per lumbar level (L4: 20 deg, Dickman 1992) within
      ``MEDIAL_TOLERANCE`` (anatomical pedicle axes run 10 deg at L1 to 30 deg at L5, Zindrick);
      sagittal angle parallel to the superior endplate within ``SAGITTAL_TOLERANCE``; every
      degree away from the textbook angles costs ``ANGLE_COST`` of clearance, so the textbook
      trajectory is kept unless another buys a wider corridor;
    - the line may pass anywhere within ``OFFSET_RANGE`` of the pedicle centre;
    - entry where the line leaves the bone posteriorly (the posterior bone surface, behind the
      canal); target at 80 % of the in-bone length from the entry toward the anterior cortex, in
      the body (in front of the canal); entry-to-target length within ``LENGTH_RANGE``.
  The bone is the vertebra's mask with one-voxel pits and holes closed (a closing by the
  6-neighbourhood, then holes filled): mask noise neither breaks a path nor narrows a corridor;
  the entry itself lies on a voxel of the mask as given.
  Radius: the largest corridor (<= 3.5 mm, 0.25 mm steps) that stays in the vertebra from 5 mm
  past the entry (the entry itself lies on an oblique surface) to the target. A corridor under
  ``MIN_RADIUS``, or no path that meets the rules, is refused: ``Landmarks.trajectory`` then
  raises a ``LandmarkError`` naming the level, the side and why. A corridor cannot exist, and is
  refused, only where the bone the rules need is absent from the mask: a pedicle narrower than
  3 mm (2 x ``MIN_RADIUS``) once closed, or no posterior surface behind the canal to enter.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from sonogym.anatomy import labels as L
from sonogym.anatomy.volume import Volume

_SPINE_ORDER = ["T11", "T12", "L1", "L2", "L3", "L4", "L5", "S1"]
_MAX_RADIUS = 0.0035  # m, a 7 mm screw
_RADIUS_STEP = 0.00025  # m, resolution of the reported radius
_TARGET_FRACTION = 0.8
_CORRIDOR_START = 0.005  # m past the entry
_BACK_RANGE = 0.045  # m searched behind the pedicle for the entry
_FORWARD_RANGE = 0.08  # m searched in front of it for the anterior cortex
_CANAL_SLABS = (0.010, 0.005)  # m, half-thickness of the axial slabs projected to find the canal
_CANAL_MIN_AREA = 15e-6  # m^2: a smaller hole in the ring is not a canal
_CANAL_MIN_SIZE = 0.004  # m, side to side and front to back: not a gap in the arch or a sliver
_CANAL_LABEL_MIN_AREA = 10e-6  # m^2 of canal label (a cord alone is ~40 mm^2)
_CANAL_MAX_OFFSET = 0.015  # m, canal centre from the vertebra's centroid, laterally
_CANAL_MAX_DEPTH = 0.045  # m, canal centre behind the vertebra's centroid, at most
_CANAL_LABELS = (L.SPINAL_CANAL, L.LABEL_IDS["spinal_cord"])

#: Closing radii (m) tried in turn on the ring's axial projection: gaps in the posterior arch up
#: to twice the radius are bridged (ground-truth masks of thin laminae, partial volume).
RING_GAP_CLOSING = (0.0, 0.0015, 0.003, 0.0045, 0.006)

#: Rotations about s (deg, each way from the patient's anterior) searched for a vertebra's
#: midsagittal plane (its plane of mirror symmetry).
MIRROR_SPAN = 30.0
#: A canal found in the mask whose centre lies further from the vertebra's midsagittal plane than
#: this (m) plus one voxel is not the spinal canal (a notch between the processes, what a mask
#: that fills the canal leaves of it).
CANAL_MIDLINE_TOLERANCE = 0.0015
#: A canal found in the mask narrower than this (m, side to side), or deeper than
#: ``CANAL_MAX_ASPECT`` times its width, is the slit a mask that fills the canal leaves of it (an
#: adult lumbar canal is 15-30 mm wide and wider than deep): the bone gives the frame instead.
CANAL_MIN_WIDTH = 0.005
CANAL_MAX_ASPECT = 1.5
#: The body's posterior wall: where the vertebra's cross-section, walking back from the body,
#: falls below this share of its largest so far.
_BODY_WALL_DROP = 0.75
#: Least share of a vertebra's voxels behind its body for a frame from the bone alone.
_MIN_POSTERIOR_SHARE = 0.15
#: Canal estimated from the body where the mask shows none: half-width and half-depth as shares
#: of the body's (adult lumbar proportions: the canal half as wide as the body, 0.46 as deep).
_CANAL_WIDTH_SHARE = 0.5
_CANAL_DEPTH_SHARE = 0.46

#: Allowed medial angle, degrees relative to the 5 deg x level rule (more medial positive).
MEDIAL_TOLERANCE = (-5.0, 10.0)
#: Allowed sagittal angle, +-degrees from parallel to the superior endplate.
SAGITTAL_TOLERANCE = 10.0
#: Clearance (m) one degree of deviation from the textbook angles must buy.
ANGLE_COST = 0.0001
#: How far (m) the line may pass from the pedicle centre, in its cross-section.
OFFSET_RANGE = 0.006
#: Entry-to-target length (m): 40-50 mm is typical at L4, shorter at L1.
LENGTH_RANGE = (0.030, 0.060)
#: Smallest corridor radius (m) a planned trajectory may have.
MIN_RADIUS = 0.0015


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
    #: where the canal comes from: "ring" (the empty region the vertebral ring encloses),
    #: "label" (spinal_canal / spinal_cord), "hull" (inside an open arch's convex hull), or
    #: "bone" (no canal in the mask: estimated from the body, module docstring)
    canal_source: str = "ring"

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
    body, corridor radius (all metres), and its angles from the textbook ones (degrees)."""

    level: str
    side: str  # "left" or "right" (the patient's)
    entry: np.ndarray
    target: np.ndarray
    radius: float
    pedicle_centre: np.ndarray
    pedicle_width: float  # m, lateral extent of the pedicle at its centre
    medial_deviation: float = 0.0  # deg, more medial than 5 deg x level when positive
    sagittal_angle: float = 0.0  # deg, toward superior when positive

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
    """Frames of the lumbar vertebrae present and planned trajectories for L1-L5, both sides.

    ``refused`` maps a level ("L1") or a (level, side) to why it has no frame or trajectory."""

    vertebrae: dict[str, VertebraFrame]
    trajectories: dict[tuple[str, str], PedicleTrajectory]
    refused: dict = field(default_factory=dict)
    name: str = "patient"

    def vertebra(self, level: str) -> VertebraFrame:
        if level in self.refused:
            raise LandmarkError(f"{self.name}: vertebra {level}: {self.refused[level]}")
        if level not in self.vertebrae:
            raise LandmarkError(
                f"{self.name}: vertebra {level} is not in this patient (present: "
                f"{sorted(self.vertebrae)}); choose a target vertebra the label map contains"
            )
        return self.vertebrae[level]

    def trajectory(self, level: str = "L4", side: str = "right") -> PedicleTrajectory:
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        self.vertebra(level)
        if (level, side) not in self.trajectories:
            why = self.refused.get((level, side), "see the vertebra mask")
            raise LandmarkError(f"{self.name}: no usable {level} {side} pedicle trajectory: {why}")
        return self.trajectories[(level, side)]

    @classmethod
    def from_patient(cls, patient: Volume) -> Landmarks:
        lab_np = patient.labels.numpy()
        ids = np.array([L.VERTEBRA_IDS[lv] for lv in _SPINE_ORDER] + list(_CANAL_LABELS), np.uint8)
        # One pass over the volume: voxel indices of every spine level (and of the canal's
        # labels), grouped by label. The mask comes from a 256-entry table (``np.isin`` on a
        # whole 1 mm volume takes ~7 bytes per voxel of temporaries).
        wanted = np.zeros(256, dtype=bool)
        wanted[ids] = True
        flat = np.flatnonzero(wanted[lab_np])
        vals = lab_np.reshape(-1)[flat]
        order = np.argsort(vals, kind="stable")
        flat, vals = flat[order], vals[order]
        bounds = np.searchsorted(vals, ids), np.searchsorted(vals, ids, side="right")
        present = [lv for k, lv in enumerate(_SPINE_ORDER) if bounds[1][k] > bounds[0][k]]
        if not any(lv in L.LUMBAR_VERTEBRAE for lv in present):
            raise LandmarkError(f"{patient.name}: no lumbar vertebra (L1-L5) in the label map")
        sp, org = patient.spacing, patient.origin
        pts, idx = {}, {}
        for k, lv in enumerate(_SPINE_ORDER):
            if lv in present:
                sel = flat[bounds[0][k] : bounds[1][k]]
                idx[lv] = np.stack(np.unravel_index(sel, lab_np.shape), 1)
                pts[lv] = org + idx[lv] * sp
        canal_sel = np.concatenate([flat[bounds[0][k] : bounds[1][k]] for k in (-2, -1)])
        canal_pts = org + np.stack(np.unravel_index(canal_sel, lab_np.shape), 1) * sp
        cents = {lv: p.mean(0) for lv, p in pts.items()}
        cut = {lv: _cut_by_fov(idx[lv], lab_np.shape) for lv in present}
        trajs: dict[tuple[str, str], PedicleTrajectory] = {}
        refused: dict = {
            lv: f"its mask touches the field of view's edge ({cut[lv]}): the scan cuts it, so its "
            "centre, frame and trajectories would be wrong"
            for lv in present
            if cut[lv] and lv in L.LUMBAR_VERTEBRAE
        }
        whole = [lv for lv in present if not cut[lv]]
        h = sp.min()

        def frames_along(s_axes: dict) -> tuple[dict, dict]:
            """Frames (and reasons for the ones that fail) given each level's s axis."""
            out, why = {}, {}
            for lv, s_ax in s_axes.items():
                try:
                    out[lv] = _vertebra_frame(lv, pts[lv], cents[lv], s_ax, h, canal_pts)
                except LandmarkError as e:
                    why[lv] = str(e).removeprefix(f"vertebra {lv}: ")
            return out, why

        # s first from the neighbours' centroids (a neighbour cut by the scan still lies along
        # the spine), then from the curve through the body centroids (the frames' origins),
        # which a rough or partial posterior arch does not move.
        first, why = frames_along({lv: _neighbour_axis(present, lv, cents) for lv in whole})
        bodies = [lv for lv in present if lv in first]
        tangents = _spine_tangents(bodies, np.array([first[lv].centre for lv in bodies]))
        second, _ = frames_along(tangents)
        frames = {lv: second.get(lv, first[lv]) for lv in first if lv in L.LUMBAR_VERTEBRAE}
        refused.update({lv: w for lv, w in why.items() if lv in L.LUMBAR_VERTEBRAE})
        for lv, frame in frames.items():
            estimated = frame if frame.canal_source == "bone" else None
            bone = _BoneField(lab_np, L.VERTEBRA_IDS[lv], idx[lv], org, sp, estimated)
            for side in ("left", "right"):
                t = plan_corridor(lv, side, frame, pts[lv], bone)
                if isinstance(t, str):
                    refused[(lv, side)] = t
                else:
                    trajs[(lv, side)] = t
        return cls(frames, trajs, refused, patient.name)


# ----------------------------------------------------------------------------- internals


def _neighbour_axis(order: list[str], level: str, points: dict) -> np.ndarray:
    """Unit s at ``level``: from the point of the level above to that of the level below in
    ``order`` (the level's own point where a neighbour is absent)."""
    i = order.index(level)
    up = points[order[i - 1]] if i > 0 else points[level]
    lo = points[order[i + 1]] if i + 1 < len(order) else points[level]
    s_ax = up - lo if len(order) > 1 else np.array([0.0, 0.0, 1.0])
    return s_ax / np.linalg.norm(s_ax)


def _spine_tangents(order: list[str], centres: np.ndarray) -> dict[str, np.ndarray]:
    """Unit tangents (toward the head) of the curve through body ``centres`` (K, 3), listed head
    to foot: a central difference between the neighbours, or at an end, the tangent of the
    quadratic through the end and its next two (a one-sided difference would be off by half the
    angle between two levels on a lordotic curve)."""
    out = {}
    if len(order) < 2:
        return out
    t = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))])
    for i, lv in enumerate(order):
        if 0 < i < len(order) - 1:
            d = centres[i - 1] - centres[i + 1]
        elif len(order) == 2:
            d = centres[0] - centres[1]
        else:
            k = [0, 1, 2] if i == 0 else [i - 2, i - 1, i]
            a, b, _ = np.polyfit(t[k], centres[k], 2)
            d = -(2 * a * t[i] + b)  # t grows toward the feet
        out[lv] = d / np.linalg.norm(d)
    return out


def _cut_by_fov(idx: np.ndarray, shape) -> str:
    """Which volume faces a mask (voxel indices (N, 3)) touches, '' when none."""
    faces = []
    for ax, name in enumerate("xyz"):
        if idx[:, ax].min() == 0:
            faces.append(f"first {name} slice")
        if idx[:, ax].max() == shape[ax] - 1:
            faces.append(f"last {name} slice")
    return ", ".join(faces)


class _BoneField:
    """One vertebra on a crop around it: nearest-voxel membership and a signed distance to its
    surface (m, positive inside; the surface lies halfway between inside and outside voxel
    centres), both at patient-frame points. Both read the mask with its one-voxel pits and holes
    closed (mask noise of rough ground truth and model output, not missing bone), so they
    neither break a path nor narrow a corridor; ``inside(raw=True)`` reads the mask as given."""

    def __init__(
        self, labels: np.ndarray, label: int, idx: np.ndarray, origin, spacing, canal=None
    ) -> None:
        pad = np.ceil(0.004 / spacing).astype(int) + 2
        lo = np.maximum(idx.min(0) - pad, 0)
        hi = np.minimum(idx.max(0) + pad + 1, labels.shape)
        raw = labels[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] == label
        crop = ndimage.binary_fill_holes(ndimage.binary_closing(raw) | raw)
        self.label = label
        self.spacing = np.asarray(spacing, np.float64)
        self.origin = np.asarray(origin, np.float64) + lo * self.spacing
        if canal is not None:
            # A canal estimated from the bone (a frame of canal_source "bone"): the mask fills
            # it, the planner must not enter it. Its elliptic cylinder along s is not bone.
            axes = [self.origin[k] + self.spacing[k] * np.arange(raw.shape[k]) for k in range(3)]
            rel = [(x - canal.canal_centre[k]).reshape([-1 if j == k else 1 for j in range(3)])
                   for k, x in enumerate(axes)]  # fmt: skip
            u, v = (sum(r * canal.rotation[k, c] for k, r in enumerate(rel)) for c in (0, 1))
            hole = (u / canal.canal_half_width) ** 2 + (v / canal.canal_half_depth) ** 2 <= 1.0
            raw, crop = raw & ~hole, crop & ~hole
        self.raw_grid, self.inside_grid = raw, crop
        half = 0.5 * float(self.spacing.min())
        # Outside voxels all get -half: only clearances inside the bone are ever asked for, and
        # an outside voxel next to the surface is exactly half a voxel from it.
        d_in = ndimage.distance_transform_edt(crop, sampling=self.spacing)
        self.sd_grid = np.where(crop, d_in - half, -half).astype(np.float32)

    def _ijk(self, p: np.ndarray) -> np.ndarray:
        return (p - self.origin) / self.spacing

    def inside(self, p: np.ndarray, raw: bool = False) -> np.ndarray:
        """(...,) whether the nearest voxel of each point (..., 3) belongs to the vertebra (its
        closed mask; the mask as given when ``raw``)."""
        grid = self.raw_grid if raw else self.inside_grid
        ijk = np.rint(self._ijk(p)).astype(np.int64)
        ok = ((ijk >= 0) & (ijk < grid.shape)).all(-1)
        ijk = np.clip(ijk, 0, np.array(grid.shape) - 1)
        return ok & grid[ijk[..., 0], ijk[..., 1], ijk[..., 2]]

    def signed_distance(self, p: np.ndarray) -> np.ndarray:
        """(...,) trilinear signed distance (m) at points (..., 3); outside the crop: negative."""
        ijk = self._ijk(p).reshape(-1, 3).T
        v = ndimage.map_coordinates(self.sd_grid, ijk, order=1, mode="constant", cval=-0.01)
        return v.reshape(p.shape[:-1])


def _project(pts: np.ndarray, origin: np.ndarray, axes: np.ndarray) -> np.ndarray:
    return (pts - origin) @ axes


def _disk(radius_cells: int) -> np.ndarray:
    r = np.arange(-radius_cells, radius_cells + 1)
    return (r[:, None] ** 2 + r[None, :] ** 2) <= radius_cells**2 + 1e-9


def _axial_projection(q: np.ndarray, h: float, pad: int):
    """Occupancy grid (U, V) of the points ``q`` (N, 3; l, a, s in m) projected along s onto
    cells of ``h``, ``pad`` empty cells around them, and the (U, V, 2) cell centres (l, a)."""
    lo = q[:, :2].min(0) - pad * h
    ij = np.floor((q[:, :2] - lo) / h).astype(int)
    grid = np.zeros(ij.max(0) + pad + 1, bool)
    grid[ij[:, 0], ij[:, 1]] = True
    return grid, lo + (np.indices(grid.shape).transpose(1, 2, 0) + 0.5) * h


def _canal_hole(hole: np.ndarray, uv: np.ndarray, h: float):
    """The component of ``hole`` that is the canal (the largest lying behind the vertebra's
    centroid, the origin of ``uv``, near its midline), as a mask; None when there is none."""
    lab, n = ndimage.label(hole)
    if n == 0:
        return None
    idx = np.arange(1, n + 1)
    area = ndimage.sum(hole, lab, idx) * h * h
    cl = np.asarray(ndimage.mean(uv[..., 0], lab, idx))
    ca = np.asarray(ndimage.mean(uv[..., 1], lab, idx))
    ok = (area >= _CANAL_MIN_AREA) & (np.abs(cl) < _CANAL_MAX_OFFSET)
    for k in range(2):  # extents along l and a
        size = np.asarray(ndimage.maximum(uv[..., k], lab, idx))
        ok &= size - np.asarray(ndimage.minimum(uv[..., k], lab, idx)) + h >= _CANAL_MIN_SIZE
    ok &= (ca < 0) & (ca > -_CANAL_MAX_DEPTH)
    return lab == idx[ok][np.argmax(area[ok])] if ok.any() else None


def _canal_from_ring(grid: np.ndarray, uv: np.ndarray, h: float):
    """Canal mask on the axial projection ``grid``: the empty region the vertebral ring encloses,
    gaps in the arch bridged by closings of growing radius (``RING_GAP_CLOSING``)."""
    for radius in RING_GAP_CLOSING:
        rc = int(round(radius / h))
        closed = ndimage.binary_closing(grid, _disk(rc)) if rc else grid
        inner = ndimage.binary_fill_holes(closed)
        region = _canal_hole(inner & ~closed, uv, h)
        if region is None:
            continue
        if rc:
            # Back into the corners the closing rounded off (a trefoil canal's lateral recesses)
            # and into the bridged gaps, within the hole's anterior-posterior span (+-r): not out
            # through a gap into the notches behind the arch.
            rows = np.flatnonzero(region.any(0))
            band = np.zeros_like(grid)
            band[:, max(rows[0] - rc, 0) : rows[-1] + rc + 1] = True
            free, _ = ndimage.label(inner & ~grid & band)
            region = free == free[region][0]
        return region
    return None


def _canal_from_hull(grid: np.ndarray, uv: np.ndarray, h: float):
    """Canal mask on the axial projection ``grid``: the empty region inside the projection's
    convex hull behind the body (an arch open wider than the closings bridge)."""
    cells = uv[grid]
    if len(cells) < 3:
        return None
    try:
        eq = ConvexHull(cells).equations
    except QhullError:  # all cells on a line
        return None
    inside = (uv @ eq[:, :2].T + eq[:, 2] <= 1e-9).all(-1)
    return _canal_hole(inside & ~grid, uv, h)


def _canal(pts, centre, l_ax, a_ax, s_ax, h, label_pts):
    """Canal centre (3,), half-width, half-depth, in axial slabs around ``centre``: from the
    vertebral ring (a slab of +-``_CANAL_SLABS[0]``, then thinner ones, where the canal narrows
    less over the slab), else the canal's own label (``label_pts``: spinal_canal and spinal_cord
    voxels), else the convex hull of the arch; None when none shows a canal."""
    rot = np.stack([l_ax, a_ax, s_ax], 1)
    q_all = _project(pts, centre, rot)
    pad = int(np.ceil(max(RING_GAP_CLOSING) / h)) + 3
    cells, projections, source = None, [], "ring"
    for slab in _CANAL_SLABS:
        q = q_all[np.abs(q_all[:, 2]) < slab]
        if len(q) < 10:
            continue
        grid, uv = _axial_projection(q, h, pad)
        projections.append((grid, uv))
        region = _canal_from_ring(grid, uv, h)
        if region is not None:
            cells = uv[region]
            break
    if not projections:
        return None
    if cells is None and len(label_pts):
        q = _project(label_pts, centre, rot)
        q = q[(np.abs(q[:, 2]) < _CANAL_SLABS[0]) & (np.abs(q[:, 0]) < _CANAL_MAX_OFFSET)]
        q = q[(q[:, 1] < 0) & (q[:, 1] > -_CANAL_MAX_DEPTH)]
        cells = (np.unique(np.floor(q[:, :2] / h), axis=0) + 0.5) * h
        cells = cells if len(cells) * h * h >= _CANAL_LABEL_MIN_AREA else None
        source = "label"
    if cells is None:
        region = _canal_from_hull(*projections[0], h)
        cells = projections[0][1][region] if region is not None else None
        source = "hull"
    if cells is None:
        return None
    c = cells.mean(0)
    half_w = (np.ptp(cells[:, 0]) + h) / 2
    half_d = (np.ptp(cells[:, 1]) + h) / 2
    return centre + c[0] * l_ax + c[1] * a_ax, half_w, half_d, source


def _scan_axes(s_ax: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(a0, l0): the patient's anterior (+y) made perpendicular to ``s_ax``, and a0 x s."""
    a0 = np.array([0.0, 1.0, 0.0]) - s_ax[1] * s_ax
    a0 /= np.linalg.norm(a0)
    return a0, np.cross(a0, s_ax)


def _mirror_fit(q, w, theta: float, cell: float, half: int) -> tuple[float, float]:
    """How well the axial projection ``q`` (N, 2; l, a in m, weights ``w``) matches its mirror
    image about the best line at angle ``theta`` (rad, from a toward l): (score in [0, 1], the
    line's lateral offset in m)."""
    c, s = np.cos(theta), np.sin(theta)
    iu = np.floor((q[:, 0] * c - q[:, 1] * s) / cell).astype(np.int64) + half
    iv = np.floor((q[:, 0] * s + q[:, 1] * c) / cell).astype(np.int64) + half
    n = 2 * half
    grid = np.bincount(iu * n + iv, w, minlength=n * n).reshape(n, n)
    grid = ndimage.gaussian_filter(grid, 1.0)
    # Overlap with the mirror about u = offset, for every offset at once: the self-convolution
    # along u (cells i and k - i pair up), summed over the rows.
    f = np.fft.rfft(grid, 2 * n, axis=0)
    conv = np.fft.irfft(f * f, 2 * n, axis=0).sum(1)
    k = int(np.argmax(conv))
    dk = 0.0
    if 0 < k < len(conv) - 1:
        y0, y1, y2 = conv[k - 1 : k + 2]
        dk = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) if y0 - 2 * y1 + y2 < 0 else 0.0
    return float(conv[k] / (grid * grid).sum()), ((k + dk + 1) / 2 - half) * cell


def _midline(pts, centroid, s_ax, h) -> tuple[np.ndarray, np.ndarray]:
    """The vertebra's midsagittal plane, from the bone alone: (a point on it at the centroid's
    level, its anterior axis, perpendicular to ``s_ax``). The plane is the one, among those
    containing s within ``MIRROR_SPAN`` of the patient's anterior, about which the vertebra's
    axial projection (on 2 mm cells) best matches its mirror image."""
    a0, l0 = _scan_axes(s_ax)
    cell = max(h, 0.002)
    # The projection gathered on cells a quarter as wide, weighted by their voxel counts: the
    # search costs the same at any voxel size.
    ij = np.floor(_project(pts, centroid, np.stack([l0, a0], 1)) / (cell / 4)).astype(np.int64)
    lo = ij.min(0)
    ny = int(ij[:, 1].max() - lo[1]) + 1
    w = np.bincount((ij[:, 0] - lo[0]) * ny + (ij[:, 1] - lo[1]))
    occupied = np.flatnonzero(w)
    q = (np.stack(np.divmod(occupied, ny), 1) + lo + 0.5) * (cell / 4)
    w = w[occupied].astype(np.float64)
    half = int(np.ceil(np.linalg.norm(q, axis=1).max() / cell)) + 4

    def best(thetas):
        scores = np.array([_mirror_fit(q, w, t, cell, half)[0] for t in thetas])
        k = int(np.argmax(scores))
        if not 0 < k < len(thetas) - 1 or scores[k - 1] - 2 * scores[k] + scores[k + 1] >= 0:
            return thetas[k]
        y0, y1, y2 = scores[k - 1 : k + 2]
        return thetas[k] + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) * (thetas[1] - thetas[0])

    span = np.radians(MIRROR_SPAN)
    coarse = best(np.arange(-span, span + 1e-9, np.radians(3.0)))
    theta = best(coarse + np.radians(np.arange(-1.5, 1.5 + 1e-9, 0.5)))
    offset = _mirror_fit(q, w, theta, cell, half)[1]
    a_ax = np.cos(theta) * a0 + np.sin(theta) * l0
    return centroid + offset * np.cross(a_ax, s_ax), a_ax


def _body_wall(v: np.ndarray, h: float) -> float | None:
    """Position along a (m) of the vertebral body's posterior wall, from ``v``, the a of the
    vertebra's voxels near its midline. Walking back from the anterior end, the cross-section's
    area rises to the body's, falls where the body ends and rises again over the pedicles and
    the arch: the wall is where it first falls below ``_BODY_WALL_DROP`` of the largest so far,
    or halfway down to the trough between body and arch where that is shallower (a canal
    partly filled in the mask); None when the area never falls."""
    top = v.max()
    k = ((top - v) / h).astype(np.int64)  # bins from the anterior end, one voxel deep
    area = ndimage.gaussian_filter1d(np.bincount(k).astype(np.float64), max(0.0015 / h, 0.5))
    run = np.maximum.accumulate(area)
    after = np.maximum.accumulate(area[::-1])[::-1]  # largest from each bin back
    depth = np.minimum(run, after) - area
    depth[run < 0.5 * area.max()] = 0.0  # not yet in the body
    t = int(np.argmax(depth))
    level = _BODY_WALL_DROP * run
    if depth[t] > 0.05 * run[t]:  # a trough between body and arch
        level = np.maximum(level, (run + area[t]) / 2)
        peak = int(np.argmax(area[: t + 1]))
    else:
        peak = int(np.argmax(area))
    below = np.flatnonzero(area[peak:] < level[peak:])
    if not len(below):
        return None
    i = peak + int(below[0])  # > peak: the peak itself is never below
    drop = area[i - 1] - area[i]
    frac = np.clip((area[i - 1] - level[i]) / drop, 0.0, 1.0) if drop > 0 else 0.5
    return float(top - (i - 0.5 + frac) * h)


def _plausible_canal(canal, midline, h: float) -> bool:
    """Whether a canal found in the mask can be the spinal canal: its centre near the
    vertebra's midsagittal plane, and not a sliver the mask leaves of it."""
    cc, hw, hd, _ = canal
    point, a_ax = midline
    off = (cc - point) - ((cc - point) @ a_ax) * a_ax
    near = np.linalg.norm(off) <= CANAL_MIDLINE_TOLERANCE + h
    return bool(near) and 2 * hw >= CANAL_MIN_WIDTH and hd <= CANAL_MAX_ASPECT * hw


def _bone_frame(level, pts, centroid, s_ax, h, midline) -> VertebraFrame:
    """The frame from the bone alone (no canal in the mask): a along the midsagittal plane, the
    body the anterior mass in front of its posterior wall, the canal behind that wall on the
    plane, sized from the body (module docstring)."""
    point, a_mid = midline
    l_mid = np.cross(a_mid, s_ax)
    q = _project(pts, point, np.stack([l_mid, a_mid, s_ax], 1))
    near = np.abs(q[:, 0]) < 0.03
    wall = _body_wall(q[near, 1], h)
    in_body = np.zeros(len(q), bool) if wall is None else near & (q[:, 1] > wall)
    behind = 0.0 if wall is None else float((q[:, 1] < wall).mean())
    if in_body.sum() < 10 or behind < _MIN_POSTERIOR_SHARE:
        raise LandmarkError(
            f"vertebra {level}: its mask has no vertebral ring around a spinal canal (no empty "
            "region behind the body inside the arch or its convex hull), the label map has no "
            "spinal_canal or spinal_cord there, and no posterior elements (pedicles, arch) lie "
            "behind its body to place one from the bone: the mask lacks its posterior arch"
        )
    half_w = np.diff(np.percentile(q[in_body, 0], [2.0, 98.0]))[0] / 2
    half_d = (q[in_body, 1].max() - wall + h / 2) / 2
    hw, hd = _CANAL_WIDTH_SHARE * half_w, _CANAL_DEPTH_SHARE * half_d
    cc = point + (wall - hd) * a_mid
    body_c = pts[in_body].mean(0)
    a_ax = body_c - cc
    a_ax -= (a_ax @ s_ax) * s_ax
    a_ax /= np.linalg.norm(a_ax)
    rot = np.stack([np.cross(a_ax, s_ax), a_ax, s_ax], 1)
    return VertebraFrame(level, body_c, rot, cc, float(hw), float(hd), "bone")


def _vertebra_frame(level, pts, centroid, s_ax, h, label_pts) -> VertebraFrame:
    """The frame from the canal the mask shows, else (lumbar levels) from the bone alone; the
    neighbours of the lumbar spine get a frame only from a canal (they only place the spine's
    curve, which a quadratic through three bodies continues where they have none)."""
    a0, l0 = _scan_axes(s_ax)
    midline = _midline(pts, centroid, s_ax, h)
    canal = _canal(pts, centroid, l0, a0, s_ax, h, label_pts)
    if canal is None or not _plausible_canal(canal, midline, h):
        if level in L.LUMBAR_VERTEBRAE:
            return _bone_frame(level, pts, centroid, s_ax, h, midline)
        raise LandmarkError(f"vertebra {level}: its mask shows no spinal canal")
    cc, hw, hd, source = canal
    rot = np.stack([l0, a0, s_ax], 1)
    # Body: voxels in front of the canal's anterior border (the body's posterior wall), within
    # 30 mm of the midline; a cut further forward drops the body's back and moves its centroid
    # forward. Two passes: the first cuts across the frame without axial rotation, which on a
    # rotated vertebra takes more of one side's posterior corner than the other's (moving the
    # centroid sideways); the second cuts in the frame the first found.
    for _ in range(2):
        q = _project(pts, cc, rot)
        body = pts[(q[:, 1] > hd) & (np.abs(q[:, 0]) < 0.03)]
        if len(body) < 10:
            raise LandmarkError(
                f"vertebra {level}: its mask has no vertebral body in front of the canal"
            )
        body_c = body.mean(0)
        a_ax = body_c - cc
        a_ax -= (a_ax @ s_ax) * s_ax
        a_ax /= np.linalg.norm(a_ax)
        l_ax = np.cross(a_ax, s_ax)
        rot = np.stack([l_ax, a_ax, s_ax], 1)
        # Re-measure the canal in the refined frame.
        canal = _canal(pts, centroid, l_ax, a_ax, s_ax, h, label_pts)
        if canal is not None and _plausible_canal(canal, midline, h):
            cc, hw, hd, source = canal
    rot = np.stack([l_ax, a_ax, s_ax], 1)
    return VertebraFrame(level, body_c, rot, cc, float(hw), float(hd), source)


@dataclass
class _Lines:
    """Candidate trajectories evaluated along their lines (arrays over candidates)."""

    anchor: np.ndarray  # (C, 3) point on the line, in the pedicle
    d: np.ndarray  # (C, 3) unit direction, posterior -> anterior
    medial: np.ndarray  # (C,) deg deviation from 5 deg x level
    sagittal: np.ndarray  # (C,) deg
    entry_t: np.ndarray = None  # (C,) m along d from the anchor
    target_t: np.ndarray = None
    clearance: np.ndarray = None  # (C,) m, min signed distance from 5 mm past entry to target
    why: np.ndarray = None  # (C,) int, 0 valid, else the rule that failed (_RULES)


_RULES = (
    "",
    "the line through the pedicle leaves the bone there",
    "the line never leaves the bone posteriorly within 45 mm",
    "the in-bone length is outside the length rule",
    "the entry is not on the posterior bone surface (behind the canal)",
    "the target is not in the vertebral body (in front of the canal)",
    "the path from entry to target leaves the bone",
)


def _directions(frame: VertebraFrame, sgn: float, nominal: float, medial, sagittal):
    """(K, 3) unit directions for medial deviations and sagittal angles (deg, flat arrays)."""
    th = np.radians(np.maximum(nominal + medial, 0.0))
    ph = np.radians(sagittal)
    horiz = np.cos(th)[:, None] * frame.anterior - sgn * np.sin(th)[:, None] * frame.lateral
    d = np.cos(ph)[:, None] * horiz + np.sin(ph)[:, None] * frame.superior
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _candidates(frame, sgn, nominal, pc, medial, sagittal, offsets) -> _Lines:
    """Every combination of (medial, sagittal) pairs and (u, v) offsets from the point pc."""
    d = _directions(frame, sgn, nominal, medial, sagittal)  # (K, 3)
    e1 = np.cross(frame.superior, d)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(d, e1)
    u, v = offsets[:, 0], offsets[:, 1]  # (M,)
    anchor = pc + u[None, :, None] * e1[:, None] + v[None, :, None] * e2[:, None]  # (K, M, 3)
    k, m = anchor.shape[:2]
    return _Lines(
        anchor.reshape(-1, 3),
        np.repeat(d, m, 0),
        np.repeat(medial, m),
        np.repeat(sagittal, m),
    )


def _walk(ins: np.ndarray, max_run: int) -> tuple[np.ndarray, np.ndarray]:
    """Walk samples (C, T) from index 0 on: (index of the last bone sample before the first run
    of more than ``max_run`` non-bone samples, whether no such run occurs)."""
    t = ins.shape[1]
    last_true = np.maximum.accumulate(np.where(ins, np.arange(t), -1), axis=1)
    broken = (np.arange(t) - last_true) > max_run
    k = np.where(broken.any(1), broken.argmax(1), t - 1)
    return last_true[np.arange(len(ins)), k], ~broken.any(1)


def _onto_raw_bone(raw: np.ndarray, start: np.ndarray, reach: int) -> np.ndarray:
    """(C,) samples from ``start`` (C,) forward to the first True of ``raw`` (C, T) within
    ``reach`` samples; 0 where there is none."""
    k = np.minimum(start[:, None] + np.arange(reach + 1), raw.shape[1] - 1)
    hit = raw[np.arange(len(raw))[:, None], k]
    return np.where(hit.any(1), hit.argmax(1), 0)


def _evaluate(lines: _Lines, bone: _BoneField, frame: VertebraFrame, step: float) -> _Lines:
    """Entry, target, clearance and rule check of every candidate line (vectorised)."""
    h = float(bone.spacing.min())
    n_back, n_fwd = int(_BACK_RANGE / step), int(_FORWARD_RANGE / step)
    ts = np.arange(-n_back, n_fwd + 1) * step  # (T,)
    c = len(lines.d)
    out_e, out_t = np.zeros(c), np.zeros(c)
    clear, why = np.full(c, -np.inf), np.zeros(c, np.int64)
    for s in range(0, c, 1024):  # chunks keep the (C, T, 3) sample array small
        sl = slice(s, min(s + 1024, c))
        pts = lines.anchor[sl, None] + ts[None, :, None] * lines.d[sl, None]
        ins = bone.inside(pts)
        w = np.where(ins[:, n_back], 0, 1)
        # Back from the anchor: the entry is the last bone sample before a gap > 1 voxel, moved
        # forward onto the first sample of the mask as given (the entry lies on bone, not in a
        # closed pit); forward: the anterior cortex is the last one before a gap > 2 voxels.
        back, open_back = _walk(ins[:, n_back::-1], int(1.01 * h / step + 1e-9))
        back -= _onto_raw_bone(bone.inside(pts, raw=True), n_back - back, int(h / step + 1))
        fwd, _ = _walk(ins[:, n_back:], int(2.01 * h / step + 1e-9))
        w[(w == 0) & open_back] = 2  # still in bone _BACK_RANGE back
        e_t = -back * step
        t_t = e_t + _TARGET_FRACTION * (fwd * step - e_t)
        length = t_t - e_t
        w[(w == 0) & ((length < LENGTH_RANGE[0]) | (length > LENGTH_RANGE[1]))] = 3
        entry = lines.anchor[sl] + e_t[:, None] * lines.d[sl]
        target = lines.anchor[sl] + t_t[:, None] * lines.d[sl]
        w[(w == 0) & ((entry - frame.canal_centre) @ frame.anterior >= 0)] = 4
        in_body = (target - frame.canal_centre) @ frame.anterior > frame.canal_half_depth
        w[(w == 0) & ~in_body] = 5
        on_path = (ts[None] >= e_t[:, None] - 1e-9) & (ts[None] <= t_t[:, None])
        w[(w == 0) & (on_path & ~ins).any(1)] = 6
        # Clearance from 5 mm past the entry (the entry itself lies on an oblique surface).
        start = e_t + np.minimum(_CORRIDOR_START, length / 2)
        ok = w == 0
        if ok.any():
            sd = bone.signed_distance(pts[ok])
            span = (ts[None] >= start[ok, None]) & (ts[None] <= t_t[ok, None])
            cl = np.full(len(w), -np.inf)
            cl[ok] = np.where(span, sd, np.inf).min(1)
            clear[sl] = cl
        out_e[sl], out_t[sl], why[sl] = e_t, t_t, w
    lines.entry_t, lines.target_t, lines.clearance, lines.why = out_e, out_t, clear, why
    return lines


def _score(lines: _Lines, h: float) -> np.ndarray:
    """Clearance (capped where the screw no longer gains) minus the cost of leaving the textbook
    angles; a tiny term for the uncapped clearance breaks ties toward the centred line."""
    dev = np.hypot(lines.medial, lines.sagittal)
    capped = np.minimum(lines.clearance, _MAX_RADIUS + _RADIUS_STEP)
    s = capped - ANGLE_COST * dev + 1e-3 * lines.clearance
    return np.where(lines.why == 0, s, -np.inf)


def plan_corridor(
    level: str, side: str, frame: VertebraFrame, pts: np.ndarray, bone: _BoneField
) -> PedicleTrajectory | str:
    """The widest-corridor trajectory within the rules (module docstring), or why there is
    none (a sentence naming the level, side and the rule that failed)."""
    h = float(bone.spacing.min())
    sgn = 1.0 if side == "right" else -1.0
    q = _project(pts, frame.canal_centre, frame.rotation)
    sel = (
        (np.abs(q[:, 1]) < 0.5 * frame.canal_half_depth)
        & (sgn * q[:, 0] > frame.canal_half_width)
        & (sgn * q[:, 0] < frame.canal_half_width + 0.015)
    )
    if sel.sum() < 3:
        return f"{level} {side}: no pedicle lateral to the canal in the vertebra mask"
    ped = pts[sel]
    pc = ped.mean(0)
    nominal = 5.0 * int(level[1])
    st = max(h, 0.001)

    def grid(half, step):
        n = int(half / step + 1e-9)
        g = np.arange(-n, n + 1) * step
        return np.stack([a.ravel() for a in np.meshgrid(g, g, indexing="ij")], 1)

    def search(anchor, med, sag, offsets, step):
        lines = _evaluate(_candidates(frame, sgn, nominal, anchor, med, sag, offsets), bone,
                          frame, step)  # fmt: skip
        return lines, _score(lines, h)

    def refine(lines, score, angle_step):
        """Finer offsets (and angles, when angle_step) around the best, sampled at h/4."""
        b = int(np.argmax(score))
        dm = np.array([-angle_step, 0.0, angle_step]) if angle_step else np.zeros(1)
        fm, fs = np.meshgrid(lines.medial[b] + dm, lines.sagittal[b] + 2 * dm, indexing="ij")
        fm, fs = fm.ravel(), fs.ravel()
        keep = (fm >= MEDIAL_TOLERANCE[0]) & (fm <= MEDIAL_TOLERANCE[1])
        keep &= np.abs(fs) <= SAGITTAL_TOLERANCE
        return search(lines.anchor[b], fm[keep], fs[keep], grid(st, st / 2), h / 4)

    # 1. Textbook angles, the line anywhere within OFFSET_RANGE of the pedicle centre.
    zero = np.zeros(1)
    lines, score = search(pc, zero, zero, grid(OFFSET_RANGE, st), h / 2)
    if np.isfinite(score).any():
        anchor = lines.anchor[int(np.argmax(score))]
        lines, score = refine(lines, score, 0.0)
    else:
        counts = np.bincount(lines.why, minlength=len(_RULES))
        rule = _RULES[int(np.argmax(counts[1:])) + 1]
        anchor = pc
    # 2. Every allowed angle pair, the line within 2 mm of that anchor, refined the same way;
    # kept only if it beats the textbook line after its angle cost.
    m_grid = np.arange(MEDIAL_TOLERANCE[0], MEDIAL_TOLERANCE[1] + 1e-9, 2.5)
    s_grid = np.arange(-SAGITTAL_TOLERANCE, SAGITTAL_TOLERANCE + 1e-9, 5.0)
    mm, ss = (a.ravel() for a in np.meshgrid(m_grid, s_grid, indexing="ij"))
    lines2, score2 = search(anchor, mm, ss, grid(0.002, st), h / 2)
    if np.isfinite(score2).any():
        lines2, score2 = refine(lines2, score2, 1.25)
        if not np.isfinite(score).any() or score2.max() > score.max():
            lines, score = lines2, score2
    if not np.isfinite(score).any():
        return (
            f"{level} {side}: no path within the rules (medial {nominal:g} deg "
            f"{MEDIAL_TOLERANCE[0]:+g}/{MEDIAL_TOLERANCE[1]:+g}, sagittal +-{SAGITTAL_TOLERANCE:g}"
            f" deg, length {LENGTH_RANGE[0] * 1e3:g}-{LENGTH_RANGE[1] * 1e3:g} mm): at the "
            f"textbook angles {rule} (is the mask a whole, binary vertebra at the right voxel "
            "size?)"
        )
    b = int(np.argmax(score))
    d = lines.d[b]
    entry = lines.anchor[b] + lines.entry_t[b] * d
    target = lines.anchor[b] + lines.target_t[b] * d
    radius = _corridor_radius(bone, entry, target, h)
    if radius < MIN_RADIUS - 1e-9:
        return (
            f"{level} {side}: the widest corridor within the rules has radius "
            f"{radius * 1e3:.2f} mm, under the {MIN_RADIUS * 1e3:g} mm minimum (a pedicle too "
            "narrow, or a mask with holes, for a screw)"
        )
    # Width across the pedicle axis, in the cross-section through the pedicle centre.
    perp = np.cross(frame.superior, d)
    perp /= np.linalg.norm(perp)
    rel = ped - pc
    near = (np.abs(rel @ d) < h) & (np.abs(rel @ frame.superior) < h)
    width = float(np.ptp(rel[near] @ perp) + h) if near.sum() > 1 else float("nan")
    return PedicleTrajectory(
        level,
        side,
        entry,
        target,
        radius,
        pc,
        width,
        float(np.degrees(np.arctan2(-sgn * d @ frame.lateral, d @ frame.anterior)) - nominal),
        float(np.degrees(np.arcsin(np.clip(d @ frame.superior, -1, 1)))),
    )


def _corridor_radius(bone: _BoneField, entry, target, h) -> float:
    """Largest radius (0.25 mm steps, <= 3.5 mm) whose rings around the axis, from 5 mm past the
    entry to the target, all fall on voxels of the vertebra (its closed mask)."""
    axis = target - entry
    length = np.linalg.norm(axis)
    d = axis / length
    e1 = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(d, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    # Samples a quarter voxel apart along the axis and around each ring (no voxel slips between)
    start = min(_CORRIDOR_START, length / 2)
    ts = np.linspace(start, length, int(np.ceil((length - start) / (h / 4))) + 1)[:, None, None]
    best = 0.0
    for r in np.arange(_RADIUS_STEP, _MAX_RADIUS + 1e-9, _RADIUS_STEP):
        ang = np.linspace(0, 2 * np.pi, max(16, int(np.ceil(2 * np.pi * r / (h / 4)))), False)
        ring = np.cos(ang)[None, :, None] * e1 + np.sin(ang)[None, :, None] * e2
        if not bone.inside(entry + ts * d + r * ring).all():
            break
        best = r
    return round(float(best), 6)
