"""Procedural lumbar phantom: a prone adult torso with L1-L5, drawn from signed distances.

``make_phantom(seed, params)`` returns a :class:`~sonogym.anatomy.patient.Patient` whose label
map uses TotalSegmentator v2 ids (plus project ids >= 118) and whose CT is in Hounsfield units
with partial-volume edges and CT noise. Anatomy is drawn in millimetres from analytic shapes:
each vertebra (body with cortical shell over a cancellous core, pedicles, laminae, spinous,
transverse and articular processes) is built in its own frame (l lateral toward the patient's
right, a anterior, s superior) and placed along a spine curve with lordosis, scoliosis and axial
rotation. Dimensions follow shared/reference/ultrasound_physics.md §4 (adult ranges).

Variability comes from named parameters (``PhantomParams``); any left ``None`` is drawn from the
seed. The same seed and params give the same volumes bit for bit.

``load_phantom`` adds an on-disk cache (``$SONOGYM_CACHE``, default ``~/.cache/sonogym``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sonogym.anatomy import labels as L
from sonogym.anatomy.cache import cached_patient
from sonogym.anatomy.patient import Patient
from sonogym.anatomy.sdf import (
    capsule,
    ellipse2,
    ellipsoid,
    extrude,
    segment2,
    smooth_union,
    superellipse2,
)

#: Bump when the generator's output changes, so stale cache entries are not reused.
GENERATOR_VERSION = 1

# ----------------------------------------------------------------------------- parameters

#: Drawn parameters: name -> (low, high). Drawn in this order from the seed, each always drawn
#: (even when given) so fixing one parameter leaves the others' draws unchanged.
_SAMPLED: dict[str, tuple[float, float]] = {
    "torso_half_width": (0.150, 0.185),  # m
    "torso_depth": (0.200, 0.250),  # m
    "fat_thickness": (0.006, 0.030),  # m
    "muscle_bulk": (0.85, 1.20),  # scale
    "vertebra_scale": (0.92, 1.08),  # scale
    "lordosis": (0.45, 0.85),  # rad, L1 vs S1 endplates (prone)
    "scoliosis": (-0.006, 0.006),  # m, peak lateral offset
    "axial_rotation": (-0.07, 0.07),  # rad, peak axial rotation
    "cancellous_hu": (150.0, 260.0),  # HU
}


@dataclass(frozen=True)
class PhantomParams:
    """Phantom parameters. ``None`` fields are drawn from the seed (ranges in ``_SAMPLED``)."""

    spacing: float = 0.001  # m, isotropic voxel size (0.0005-0.002)
    torso_half_width: float | None = None  # m, half the back's width
    torso_depth: float | None = None  # m, back-to-belly
    fat_thickness: float | None = None  # m, subcutaneous fat
    muscle_bulk: float | None = None  # unitless scale of the paraspinal and psoas muscles
    vertebra_scale: float | None = None  # unitless scale of every vertebra
    lordosis: float | None = None  # rad, angle between the L1 and S1 endplates
    scoliosis: float | None = None  # m, peak lateral deviation of the spine (sign = side)
    axial_rotation: float | None = None  # rad, peak axial rotation of the vertebrae
    cancellous_hu: float | None = None  # HU of cancellous bone (bone density)
    cortical_hu: float = 1400.0  # HU of cortical bone
    ct_noise_hu: float = 15.0  # HU, std of Gaussian CT noise
    fov_inferior: float = 0.125  # m, field of view below the L4 centre
    fov_superior: float = 0.145  # m, field of view above the L4 centre

    def __post_init__(self) -> None:
        if not 0.0005 <= self.spacing <= 0.002:
            raise ValueError(
                f"phantom spacing {self.spacing} m is outside 0.0005-0.002 m (0.5-2.0 mm)"
            )
        if self.fov_inferior < 0.12 or self.fov_superior < 0.12:
            raise ValueError("the field of view must cover at least 0.12 m either side of L4")

    def resolved(self, seed: int) -> PhantomParams:
        """A copy with every ``None`` field drawn from ``seed``."""
        rng = np.random.default_rng(seed)
        draws = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in _SAMPLED.items()}
        return dataclasses.replace(
            self, **{k: v for k, v in draws.items() if getattr(self, k) is None}
        )


# Per-level dimensions, mm (scale 1): body half-width, half-depth, half-height; canal
# half-width, half-depth; pedicle width, height; pedicle medial angle (deg); transverse-process
# half-span; spinous-process length. Ranges of ultrasound_physics.md §4a.
_LEVEL_DIMS: dict[str, tuple[float, ...]] = {
    "T12": (19.0, 15.0, 11.5, 9.5, 8.0, 7.0, 15.0, 5.0, 30.0, 28.0),
    "L1": (20.5, 16.0, 12.5, 10.5, 8.5, 8.0, 15.0, 8.0, 34.0, 30.0),
    "L2": (21.5, 16.5, 13.0, 10.5, 8.5, 8.5, 15.0, 10.0, 38.0, 31.0),
    "L3": (22.5, 17.0, 13.5, 11.0, 8.5, 10.0, 15.0, 14.0, 45.0, 31.0),
    "L4": (23.5, 17.0, 13.5, 11.5, 8.5, 11.5, 14.0, 18.0, 40.0, 29.0),
    "L5": (25.0, 17.5, 13.0, 12.5, 8.5, 14.0, 14.0, 25.0, 43.0, 26.0),
    "S1": (26.0, 18.0, 12.5, 13.0, 7.0, 14.0, 14.0, 25.0, 0.0, 10.0),
}
#: Disc heights (mm) below each level.
_DISC_BELOW = {"T12": 7.0, "L1": 8.0, "L2": 9.0, "L3": 10.0, "L4": 11.0, "L5": 10.0}
_LEVELS = ["T12", "L1", "L2", "L3", "L4", "L5", "S1"]

# Tissue HU (ultrasound_physics.md §4c).
_HU = {
    "air": -1000.0,
    "soft": 20.0,
    "fat": -100.0,
    "skin": 30.0,
    "muscle": 50.0,
    "liver": 55.0,
    "kidney": 30.0,
    "blood": 40.0,
    "disc": 80.0,
    "csf": 15.0,
    "cord": 35.0,
}
_SKIN_MM = 2.5
_LIGAMENT_MM = 5.0  # supraspinous soft tissue between spinous tips and fat
_GROOVE_MM = 4.0  # midline groove of the back between the erector bulges


@dataclass
class _Vertebra:
    level: str
    label: int
    centre: np.ndarray  # (3,) mm, world
    rot: np.ndarray  # (3, 3) columns l, a, s in world
    dims: tuple[float, ...]  # scaled _LEVEL_DIMS

    def to_world(self, q: tuple[float, float, float]) -> np.ndarray:
        return self.centre + self.rot @ np.asarray(q, dtype=np.float64)

    @property
    def canal_a(self) -> float:
        return -self.dims[1] - self.dims[4]


# ----------------------------------------------------------------------------- spine


def _spine(p: PhantomParams) -> list[_Vertebra]:
    """Place T12..S1 along a lordotic, scoliotic curve; L4's body centre at z = 0."""
    sc = p.vertebra_scale
    dims = {
        k: tuple(v * sc if i != 7 else v for i, v in enumerate(d)) for k, d in _LEVEL_DIMS.items()
    }
    # Arc-length position of each body centre, L4 at 0, positive upward.
    arc = {"L4": 0.0}
    order = _LEVELS
    i4 = order.index("L4")
    for i in range(i4 - 1, -1, -1):  # upward
        lo, up = order[i + 1], order[i]
        arc[up] = arc[lo] + dims[lo][2] + _DISC_BELOW[up] * sc + dims[up][2]
    for i in range(i4 + 1, len(order)):  # downward
        up, lo = order[i - 1], order[i]
        arc[lo] = arc[up] - dims[up][2] - _DISC_BELOW[up] * sc - dims[lo][2]
    s_lo, s_hi = arc["S1"], arc["T12"]
    apex = arc["L3"]
    kappa = p.lordosis / (arc["L1"] - arc["S1"])  # rad per mm (constant curvature)

    s_grid = np.arange(s_lo - 60.0, s_hi + 60.0, 0.25)
    phi = -kappa * (s_grid - apex)
    span = np.clip((s_grid - s_lo) / (s_hi - s_lo), 0, 1)
    x = p.scoliosis * 1e3 * np.sin(np.pi * span)
    psi = p.axial_rotation * np.sin(np.pi * span)
    ds = 0.25
    y = np.cumsum(np.sin(phi)) * ds
    z = np.cumsum(np.cos(phi)) * ds
    k0 = int(np.argmin(np.abs(s_grid)))
    y, z = y - y[k0], z - z[k0]
    dx = np.gradient(x, ds)

    out = []
    for lev in order:
        k = int(np.argmin(np.abs(s_grid - arc[lev])))
        t = np.array([dx[k], np.sin(phi[k]), np.cos(phi[k])])
        s_ax = t / np.linalg.norm(t)
        a0 = np.array([0.0, 1.0, 0.0]) - s_ax[1] * s_ax
        a0 /= np.linalg.norm(a0)
        l0 = np.cross(a0, s_ax)
        c, s = math.cos(psi[k]), math.sin(psi[k])
        l_ax, a_ax = c * l0 + s * a0, -s * l0 + c * a0
        rot = np.stack([l_ax, a_ax, s_ax], 1)
        out.append(
            _Vertebra(lev, L.VERTEBRA_IDS[lev], np.array([x[k], y[k], z[k]]), rot, dims[lev])
        )
    return out


def _vertebra_sdf(
    v: _Vertebra, lq: torch.Tensor, aq: torch.Tensor, sq: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """SDF (mm) of a vertebra in its local frame; returns (bone, body part)."""
    bw, bd, bh, cw, cd, pw, ph, ang, tps, spl = v.dims
    body = extrude(superellipse2(lq, aq, bw - 1.5, bd - 1.5, 2.6), sq, bh - 1.5) - 1.5
    a_c = v.canal_a
    canal = extrude(ellipse2(lq, aq - a_c, cw, cd), sq, bh + 12.0)
    s_p = 0.25 * bh
    th = math.radians(ang)
    sn, cs = math.sin(th), math.cos(th)
    a_back = a_c - cd  # posterior border of the canal
    post = None
    for side in (1.0, -1.0):
        ul, ua = lq - side * (cw + pw / 2), aq - a_c
        u = ul * (-side * sn) + ua * cs  # along the pedicle axis, anterior positive
        w = ul * cs + ua * (side * sn)
        half = (cd + 8.0) / cs
        parts = [extrude(ellipse2(w, sq - s_p, pw / 2, ph / 2), u, half)]
        parts.append(
            extrude(
                segment2(lq, aq, (side * (cw + 2.0), a_back + 1.0), (0.0, a_back - 5.0)) - 3.0,
                sq + 0.15 * bh,
                0.75 * bh,
            )
        )
        if tps > 0:
            parts.append(
                capsule(
                    lq,
                    aq,
                    sq,
                    (side * (cw + pw / 2 + 1), a_back + 3, s_p),
                    (side * tps, a_back - 1, s_p + 3),
                    4.5,
                )
            )
        parts.append(
            capsule(
                lq,
                aq,
                sq,
                (side * (cw + 6), a_back - 2, s_p),
                (side * (cw + 6.5), a_back - 5, bh + 7),
                3.5,
            )
        )
        parts.append(
            capsule(
                lq,
                aq,
                sq,
                (side * (cw - 1), a_back - 6, -0.2 * bh),
                (side * (cw - 1.5), a_back - 9, -bh - 8),
                3.5,
            )
        )
        if v.level == "S1":  # sacral ala, toward the sacroiliac joint
            parts.append(
                capsule(
                    lq, aq, sq, (side * bw * 0.6, -4.0, 0.0), (side * 52.0, a_c + 2, -8.0), 12.0
                )
            )
        for part in parts:
            post = part if post is None else smooth_union(post, part, 2.0)
    spinous = extrude(
        segment2(aq, sq, (a_back - 4.0, -0.1 * bh), (a_back - 4.0 - spl, -0.1 * bh - 8.0)) - 7.5,
        lq,
        3.0,
    )
    post = smooth_union(post, spinous, 2.0)
    bone = smooth_union(body, post, 1.5)
    bone = torch.maximum(bone, -canal)
    return bone, body


# ----------------------------------------------------------------------------- canvas


class _Canvas:
    """Label and CT volumes on the phantom grid, painted structure by structure (mm units)."""

    def __init__(self, lo: np.ndarray, shape: tuple[int, int, int], h: float) -> None:
        self.lo, self.shape, self.h = lo, shape, h
        self.ct = torch.full(shape, _HU["air"], dtype=torch.float32)
        self.labels = torch.zeros(shape, dtype=torch.uint8)
        self.axes = [
            torch.tensor(lo[i] + h * np.arange(shape[i]), dtype=torch.float32) for i in range(3)
        ]

    def box(self, bmin, bmax):
        """Index slices covering the world box [bmin, bmax] (mm), or None if empty."""
        sl = []
        for i in range(3):
            i0 = max(int(math.floor((bmin[i] - self.lo[i]) / self.h)) - 1, 0)
            i1 = min(int(math.ceil((bmax[i] - self.lo[i]) / self.h)) + 2, self.shape[i])
            if i1 <= i0:
                return None
            sl.append(slice(i0, i1))
        return tuple(sl)

    def coords(self, sl):
        x, y, z = (self.axes[i][sl[i]] for i in range(3))
        return x[:, None, None], y[None, :, None], z[None, None, :]

    def paint(self, sl, sdf: torch.Tensor, label: int, hu) -> None:
        """Write ``label`` where sdf < 0 and blend CT by partial volume (occupancy of the voxel)."""
        occ = (0.5 - sdf / self.h).clamp_(0, 1)
        ct = self.ct[sl]
        hu_t = hu if isinstance(hu, torch.Tensor) else torch.tensor(hu, dtype=torch.float32)
        ct += occ * (hu_t - ct)
        self.labels[sl][sdf < 0] = label

    def z_chunks(self, n: int = 24):
        for k0 in range(0, self.shape[2], n):
            yield (slice(None), slice(None), slice(k0, min(k0 + n, self.shape[2])))


def _local(v: _Vertebra, x, y, z):
    dx, dy, dz = x - v.centre[0], y - v.centre[1], z - v.centre[2]
    r = v.rot
    return (
        dx * r[0, 0] + dy * r[1, 0] + dz * r[2, 0],
        dx * r[0, 1] + dy * r[1, 1] + dz * r[2, 1],
        dx * r[0, 2] + dy * r[1, 2] + dz * r[2, 2],
    )


def _local_box(v: _Vertebra, lo, hi):
    corners = np.array(
        [[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])]
    )
    world = v.centre + corners @ v.rot.T
    return world.min(0), world.max(0)


# ----------------------------------------------------------------------------- generator


def make_phantom(seed: int = 0, params: PhantomParams | None = None) -> Patient:
    """Build the procedural phantom for ``seed`` (deterministic; no I/O)."""
    p = (params or PhantomParams()).resolved(seed)
    h = p.spacing * 1e3
    verts = _spine(p)
    by = {v.level: v for v in verts}

    # Anchor lines of the back, as functions of z (mm): spinous tips, transverse-process tips.
    def anchor(q_fn):
        pts = np.array([v.to_world(q_fn(v)) for v in verts if v.level != "S1"])
        order = np.argsort(pts[:, 2])
        return pts[order]

    tips = anchor(
        lambda v: (0.0, v.canal_a - v.dims[4] - 4.0 - v.dims[9] - 7.5, -0.1 * v.dims[2] - 8.0)
    )
    tps = anchor(lambda v: (0.0, v.canal_a - v.dims[4] + 1.0, 0.25 * v.dims[2]))
    bodies = np.array(sorted((v.centre for v in verts), key=lambda c: c[2]))

    fat = p.fat_thickness * 1e3
    half_w = p.torso_half_width * 1e3
    depth = p.torso_depth * 1e3
    z_lo, z_hi = -p.fov_inferior * 1e3, p.fov_superior * 1e3
    zz = np.arange(z_lo - 20, z_hi + 20, 1.0)
    y_skin_mid = np.interp(zz, tips[:, 2], tips[:, 1]) - (_SKIN_MM + fat + _LIGAMENT_MM)
    y_post = y_skin_mid - _GROOVE_MM
    lo = np.array([-(half_w + 12.0), y_post.min() - 12.0, z_lo])
    hi = np.array([half_w + 12.0, y_post.max() + depth + 12.0, z_hi])
    lo = np.round(lo / h) * h
    shape = tuple(int(round((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    cv = _Canvas(lo, shape, h)

    def zf(arr_z, arr_v, z):  # interpolate an anchor line at grid z (tensor (1,1,nz))
        return torch.tensor(np.interp(z.flatten().numpy(), arr_z, arr_v), dtype=torch.float32).view(
            1, 1, -1
        )

    m = p.muscle_bulk
    # --- torso, soft-tissue layers and muscles, slab by slab
    for sl in cv.z_chunks():
        x, y, z = cv.coords(sl)
        yp = zf(zz, y_post, z)
        yc = yp + depth / 2
        taper = 1.0 + 0.06 * (-z / 125.0).clamp(-1, 1)
        torso = superellipse2(
            x / (half_w * taper), (y - yc) / (depth / 2), 1.0, 1.0, 2.3
        ) * torch.minimum(half_w * taper, torch.full_like(taper, depth / 2))
        back = ((yc - y) / (depth / 2)).clamp(0, 1)
        torso = torso + _GROOVE_MM * torch.exp(-(x**2) / (2 * 18.0**2)) * back
        cv.paint(sl, torso, L.BODY_TRUNC, _HU["soft"])
        # Paraspinal muscles (autochthon): from the transverse processes to under the fat.
        y_front = zf(tps[:, 2], tps[:, 1], z) + 8.0
        y_back = zf(zz, y_skin_mid, z)
        cy, ry = (y_front + y_back) / 2, (y_front - y_back) / 2 + 4.0
        xs = zf(bodies[:, 2], bodies[:, 0], z)
        for side, lab in ((1.0, 87), (-1.0, 86)):
            d = ellipse2(x - xs - side * 36.0 * m, (y - cy) / ry * 30.0, 36.0 * m, 30.0)
            cv.paint(sl, torch.maximum(d, torso), lab, _HU["muscle"])
        # Skin and subcutaneous fat as layers under the surface.
        fat_sdf = torch.maximum(-(torso + _SKIN_MM + fat), torso + _SKIN_MM)
        cv.paint(sl, fat_sdf, L.SUBCUTANEOUS_FAT, _HU["fat"])
        skin_sdf = torch.maximum(-(torso + _SKIN_MM), torso)
        cv.paint(sl, skin_sdf, L.SKIN, _HU["skin"])

    yb = lambda zv: float(np.interp(zv, bodies[:, 2], bodies[:, 1]))  # noqa: E731
    xb = lambda zv: float(np.interp(zv, bodies[:, 2], bodies[:, 0]))  # noqa: E731
    l1, l2, l4, l5, t12 = by["L1"], by["L2"], by["L4"], by["L5"], by["T12"]
    bd = l4.dims[1]

    def blob(label, hu, centre, radii, clip_body=True):
        c = np.asarray(centre)
        r = np.asarray(radii)
        sl = cv.box(c - r, c + r)
        if sl is None:
            return
        x, y, z = cv.coords(sl)
        d = ellipsoid(x - c[0], y - c[1], z - c[2], *r)
        if clip_body:
            d = torch.where(cv.labels[sl] == L.BODY_TRUNC, d, d.clamp_min(0.5 * cv.h + 1e-3))
        cv.paint(sl, d, label, hu)

    def tube(label, hu, a, b, r):
        a, b = np.asarray(a, float), np.asarray(b, float)
        sl = cv.box(np.minimum(a, b) - r, np.maximum(a, b) + r)
        if sl is None:
            return
        x, y, z = cv.coords(sl)
        cv.paint(sl, capsule(x, y, z, tuple(a), tuple(b), r), label, hu)

    # --- organs (only inside generic soft tissue, never over muscle, fat or skin)
    blob(5, _HU["liver"], (65.0, yb(t12.centre[2]) + 80, t12.centre[2] + 55), (115.0, 95.0, 105.0))
    zk = l2.centre[2]
    blob(3, _HU["kidney"], (-(l2.dims[0] + 52), yb(zk) + 12, zk + 5), (26.0, 22.0, 52.0))
    blob(2, _HU["kidney"], (l2.dims[0] + 52, yb(zk) + 12, zk - 12), (26.0, 22.0, 52.0))

    # --- iliopsoas, growing caudally
    z_top = t12.centre[2]
    sl = cv.box(np.array([-120.0, lo[1], z_lo]), np.array([120.0, hi[1], z_top]))
    x, y, z = cv.coords(sl)
    zc = z.clamp(l5.centre[2], l1.centre[2])
    grow = ((l1.centre[2] - zc) / (l1.centre[2] - l5.centre[2])).clamp(0, 1)
    below = (l5.centre[2] - z).clamp_min(0)
    yb_t = zf(bodies[:, 2], bodies[:, 1], z)
    xs_t = zf(bodies[:, 2], bodies[:, 0], z)
    rx, ry = (8.0 + 14.0 * grow) * m, (9.0 + 11.0 * grow) * m
    for side, lab in ((1.0, 89), (-1.0, 88)):
        cx = xs_t + side * (l4.dims[0] + rx * 0.8 + 0.4 * below)
        d = ellipse2((x - cx) / rx, (y - yb_t - 4.0 - 0.3 * below) / ry, 1.0, 1.0) * torch.minimum(
            rx, ry
        )
        d = torch.maximum(d, z - z_top)
        d = torch.where(cv.labels[sl] == L.BODY_TRUNC, d, d.clamp_min(0.5 * cv.h + 1e-3))
        cv.paint(sl, d, lab, _HU["muscle"])

    # --- great vessels
    z_bif = l4.centre[2] - 8.0
    ya = lambda zv: yb(zv) + bd + 13.0  # noqa: E731
    tube(
        52,
        _HU["blood"],
        (xb(z_bif) - 14, ya(z_bif), z_bif),
        (xb(z_hi) - 14, ya(z_hi), z_hi + 10),
        10.0,
    )
    z_ivc = l5.centre[2] + 5.0
    tube(
        63,
        _HU["blood"],
        (xb(z_ivc) + 20, ya(z_ivc) + 1, z_ivc),
        (xb(z_hi) + 20, ya(z_hi) + 1, z_hi + 10),
        11.0,
    )
    ybot = yb(z_lo) + bd + 25.0
    tube(65, _HU["blood"], (xb(z_bif) - 14, ya(z_bif), z_bif), (-50.0, ybot, z_lo - 10), 6.5)
    tube(66, _HU["blood"], (xb(z_bif) - 14, ya(z_bif), z_bif), (45.0, ybot, z_lo - 10), 6.5)
    tube(
        67, _HU["blood"], (xb(z_ivc) + 20, ya(z_ivc) + 1, z_ivc), (-40.0, ybot + 10, z_lo - 10), 7.5
    )
    tube(
        68, _HU["blood"], (xb(z_ivc) + 20, ya(z_ivc) + 1, z_ivc), (55.0, ybot + 10, z_lo - 10), 7.5
    )

    # --- discs between consecutive bodies
    for up, low in zip(verts[:-1], verts[1:], strict=True):
        e_up = up.centre - up.dims[2] * up.rot[:, 2]
        e_lo = low.centre + low.dims[2] * low.rot[:, 2]
        c = (e_up + e_lo) / 2
        rot = up.rot + low.rot
        s_ax = rot[:, 2] / np.linalg.norm(rot[:, 2])
        a_ax = rot[:, 1] - (rot[:, 1] @ s_ax) * s_ax
        a_ax /= np.linalg.norm(a_ax)
        dv = _Vertebra("disc", 0, c, np.stack([np.cross(a_ax, s_ax), a_ax, s_ax], 1), ())
        hh = np.linalg.norm(e_up - e_lo) / 2 + 1.0
        rw, rd = min(up.dims[0], low.dims[0]) * 0.97, min(up.dims[1], low.dims[1]) * 0.97
        bmin, bmax = _local_box(dv, (-rw, -rd, -hh), (rw, rd, hh))
        sl = cv.box(bmin, bmax)
        if sl is None:
            continue
        lq, aq, sq = _local(dv, *cv.coords(sl))
        cv.paint(
            sl,
            extrude(superellipse2(lq, aq, rw, rd, 2.6), sq, hh),
            L.INTERVERTEBRAL_DISCS,
            _HU["disc"],
        )

    # --- spinal canal, cord, vertebrae (canal first: vertebrae are carved around it)
    for v in verts:
        bw, bdv, bh, cw, cd = v.dims[:5]
        reach = max(bw + 60.0, v.dims[8] + 8.0)
        bmin, bmax = _local_box(
            v, (-reach, v.canal_a - cd - v.dims[9] - 25, -bh - 30), (reach, bdv + 3, bh + 30)
        )
        sl = cv.box(bmin, bmax)
        if sl is None:
            continue
        lq, aq, sq = _local(v, *cv.coords(sl))
        canal = extrude(ellipse2(lq, aq - v.canal_a, cw, cd), sq, bh + 12.0)
        cv.paint(sl, canal, L.SPINAL_CANAL, _HU["csf"])
        if v.level in ("T12", "L1"):  # the cord ends (conus) at the L1 body
            s0 = -0.2 * bh if v.level == "L1" else -bh - 12.0
            cord = extrude(
                ellipse2(lq, aq - v.canal_a, 4.5, 4.0), sq - (s0 + bh + 12) / 2, (bh + 12 - s0) / 2
            )
            cv.paint(sl, cord, 79, _HU["cord"])
        bone, body = _vertebra_sdf(v, lq, aq, sq)
        t_cortex = torch.where(body <= bone + 0.5, 1.0, 2.0)
        hu = p.cancellous_hu + (p.cortical_hu - p.cancellous_hu) * (
            (bone + t_cortex) / cv.h + 0.5
        ).clamp(0, 1)
        cv.paint(sl, bone, v.label, hu)

    # --- sacrum below S1: two tapering segments bending posteriorly, with alae
    s1 = by["S1"]
    for k, (ds, da, rw, rd, hh) in enumerate(
        ((24.0, -5.0, 21.0, 12.0, 9.0), (42.0, -13.0, 15.0, 9.0, 8.0))
    ):
        c = s1.to_world((0.0, da, -s1.dims[2] - ds + 12.0))
        sv = _Vertebra("S", 25, c, s1.rot, ())
        bmin, bmax = _local_box(sv, (-60, -40, -hh - 6), (60, 25, hh + 6))
        sl = cv.box(bmin, bmax)
        if sl is None:
            continue
        lq, aq, sq = _local(sv, *cv.coords(sl))
        seg = extrude(superellipse2(lq, aq, rw, rd, 2.4), sq, hh)
        dorsal = extrude(segment2(lq, aq, (-rw * 0.8, -rd - 6), (rw * 0.8, -rd - 6)) - 4.0, sq, hh)
        seg = smooth_union(seg, dorsal, 3.0)
        if k == 0:
            for side in (1.0, -1.0):
                seg = smooth_union(
                    seg,
                    capsule(
                        lq, aq, sq, (side * rw * 0.5, -3.0, 0.0), (side * 48.0, -8.0, 2.0), 9.0
                    ),
                    3.0,
                )
        hu = p.cancellous_hu + (p.cortical_hu - p.cancellous_hu) * ((seg + 1.5) / cv.h + 0.5).clamp(
            0, 1
        )
        cv.paint(sl, seg, 25, hu)

    # --- iliac wings (hip_left 77, hip_right 78): curved plates, crest near the L4/L5 disc
    z_crest = (l4.centre[2] - l4.dims[2] + l5.centre[2] + l5.dims[2]) / 2 + 4.0
    yc_il = yb(l5.centre[2]) - 5.0
    for side, lab in ((-1.0, 77), (1.0, 78)):
        cx = side * 72.0
        sl = cv.box(
            np.array([cx - 60, yc_il - 75, z_lo]), np.array([cx + 60, yc_il + 75, z_crest + 2])
        )
        x, y, z = cv.coords(sl)
        dx, dy = x - cx, y - yc_il
        shell = ellipse2(dx, dy, 47.0, 66.0).abs() - 3.5
        shell = torch.maximum(shell, -side * dx - 26.0)
        shell = torch.maximum(shell, dy - 35.0)
        shell = torch.maximum(shell, z - (z_crest - 0.002 * dy**2))
        hu = p.cancellous_hu + (p.cortical_hu - p.cancellous_hu) * (
            (shell + 2.0) / cv.h + 0.5
        ).clamp(0, 1)
        cv.paint(sl, shell, lab, hu)

    # --- lower ribs (11 and 12) from T12 and the level above
    for side, r11, r12 in ((-1.0, 102, 103), (1.0, 114, 115)):
        a_c = t12.canal_a
        cw = t12.dims[3]
        p0 = t12.to_world((side * (cw + 10), a_c - 2, 3.0))
        p1 = t12.to_world((side * 45, a_c - 8, -20.0))
        p2 = t12.to_world((side * 85, a_c + 15, -45.0))
        q0 = t12.to_world((side * (cw + 10), a_c - 2, 39.0))
        q1 = t12.to_world((side * 55, a_c - 10, 10.0))
        q2 = t12.to_world((side * 110, a_c + 35, -25.0))
        for lab, seg, r in (
            (r12, (p0, p1), 4.5),
            (r12, (p1, p2), 4.5),
            (r11, (q0, q1), 5.0),
            (r11, (q1, q2), 5.0),
        ):
            a, b = seg
            sl = cv.box(np.minimum(a, b) - r, np.maximum(a, b) + r)
            if sl is None:
                continue
            x, y, z = cv.coords(sl)
            d = capsule(x, y, z, tuple(a), tuple(b), r)
            hu = p.cancellous_hu + (p.cortical_hu - p.cancellous_hu) * (
                (d + 1.5) / cv.h + 0.5
            ).clamp(0, 1)
            cv.paint(sl, d, lab, hu)

    # --- CT noise, integer HU (so the int16 NIfTI round trip is exact)
    gen = torch.Generator().manual_seed(int(seed))
    noise = torch.randn(shape, generator=gen, dtype=torch.float32)
    ct = (cv.ct + p.ct_noise_hu * noise).round_().clamp_(-1024, 3071)

    affine = np.diag([p.spacing, p.spacing, p.spacing, 1.0])
    affine[:3, 3] = lo * 1e-3
    meta = {
        "source": "sonogym.make_phantom",
        "seed": int(seed),
        "generator_version": GENERATOR_VERSION,
        "params": dataclasses.asdict(p),
        "vertebrae": {
            v.level: {"centre_m": (v.centre * 1e-3).tolist(), "rotation": v.rot.tolist()}
            for v in verts
        },
    }
    return Patient(ct=ct, labels=cv.labels, affine=affine, name=f"phantom-{seed}", meta=meta)


# ----------------------------------------------------------------------------- cache


def cache_dir() -> Path:
    """Where cached phantoms live: ``$SONOGYM_CACHE`` or ``~/.cache/sonogym``."""
    return Path(os.environ.get("SONOGYM_CACHE", Path.home() / ".cache" / "sonogym"))


#: Disk bytes of one cache entry at 1 mm voxels (CT int16 + labels uint8 in an uncompressed
#: .npz): 65-84 MB measured for seeds 0-5, 7 and 8 (17-21 s to build each). An entry scales
#: with the voxel count, (1 mm / spacing)^3 (seed 0: 74 MB at 1 mm, 9.2 MB at 2 mm).
CACHE_ENTRY_BYTES_1MM = 90e6


def cache_entry_bytes(spacing: float) -> float:
    """Estimated disk bytes of one cached phantom at ``spacing`` (m)."""
    return CACHE_ENTRY_BYTES_1MM * (1e-3 / spacing) ** 3


def is_cached(seed: int, params: PhantomParams | None = None) -> bool:
    """Whether ``load_phantom(seed, params)`` finds an entry in ``cache_dir()`` (not verified)."""
    stem = cache_dir() / f"phantom-{seed}-{phantom_cache_key(seed, params)}"
    return stem.with_suffix(".npz").exists()


def phantom_cache_key(seed: int, params: PhantomParams | None = None) -> str:
    """Stable key of a phantom: generator version, seed and resolved parameters."""
    p = (params or PhantomParams()).resolved(seed)
    blob = json.dumps(
        {"v": GENERATOR_VERSION, "seed": int(seed), "params": dataclasses.asdict(p)}, sort_keys=True
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def load_phantom(
    seed: int = 0, params: PhantomParams | None = None, cache: bool | Path = True
) -> Patient:
    """``make_phantom`` with an on-disk cache keyed by seed and parameters.

    ``cache``: True for :func:`cache_dir`, a folder, or False to always build.

    An entry is ``phantom-<seed>-<key>.npz`` (the CT as int16 and the labels, no pickle) and a
    ``.json`` sidecar (name, affine, provenance and a SHA-256 of all of it), each written to a
    temporary file and renamed, so readers never see a partial entry. An entry that does not
    verify is reported with a warning naming it and rebuilt; temporary files left by killed
    writers are removed.
    """
    if cache is False:
        return make_phantom(seed, params)
    folder = cache_dir() if cache is True else Path(cache)
    stem = folder / f"phantom-{seed}-{phantom_cache_key(seed, params)}"
    patient = cached_patient(stem, lambda: make_phantom(seed, params), "phantom")
    stem.with_suffix(".pt").unlink(missing_ok=True)  # the old pickle format of this entry
    return patient
