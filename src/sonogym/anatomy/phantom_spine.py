"""Bones of the procedural phantom: per-level lumbar dimensions, the spine's placement, and each
vertebra, the sacrum and the iliac bones as signed-distance parts.

Coordinates are millimetres. Each vertebra has a frame (l toward the patient's right, a anterior,
s superior) with its origin at the body centre; the spine's frames come from a lordotic,
scoliotic, axially rotated curve (``place_spine``). A bone is a list of ``Part``s, each an SDF in
its own frame with a bounding box there, so that a part is evaluated only where it can matter
(``draw_parts`` in ``phantom``); parts of one bone are joined with a fillet.

What a lumbar vertebra is made of (docs/anatomy.md has the figure and the sources):

* body: kidney-shaped cross-section (a superellipse with a concave posterior wall), a waist at
  mid-height, slightly concave endplates;
* pedicles: elliptical struts from the body's posterolateral corner to the pedicle-lamina
  junction, angled medially;
* laminae: one plate per side from the junction to the midline, leaning posteriorly toward
  their lower edge (the shingles of the paramedian view), joined at the midline with the
  spinous process: one continuous arch roofing the canal;
* spinous process: a sagittal plate, thicker toward its rounded, club-shaped tip;
* superior and inferior articular processes: plates oriented along the facet joint (angled from
  the sagittal plane: 25 deg at L1-2 to 50 deg at L5-S1), the inferior process of one level
  facing the superior process of the next across a 2 mm joint space;
* transverse processes: flat bars from the junction to tip, slightly posterior at the tip.

The sacrum has S1 (vertebrae_S1) with its body, superior articular processes, alae and the first
median-crest tubercle, then S2-S4 (sacrum) bending anteriorly, each with its dorsal plate,
median crest and lateral mass. The iliac bones are curved plates whose crest peaks beside L4-L5
and whose posterior end (PSIS) lies beside the upper sacrum.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from sonogym.anatomy import labels as L
from sonogym.anatomy.sdf import (
    capsule,
    ellipse2,
    polygon2,
    round_box,
    segment2,
    smooth_subtract,
    superellipse2,
)

Tensor = torch.Tensor
LEVELS = ("T12", "L1", "L2", "L3", "L4", "L5", "S1")


@dataclass(frozen=True)
class LevelDims:
    """One level's dimensions (mm, degrees) at scale 1. Sources: docs/anatomy.md."""

    body_half_width: float  # half the endplate width
    body_half_depth: float  # half the endplate depth
    body_half_height: float  # half the posterior body height
    canal_half_width: float
    canal_half_depth: float
    pedicle_width: float  # transverse
    pedicle_height: float
    pedicle_angle: float  # deg, medial convergence
    tp_half_span: float  # midline to transverse-process tip
    spinous_length: float  # canal's posterior border to spinous tip
    spinous_height: float  # cranio-caudal height of the tip
    lamina_thickness: float
    facet_half_distance: float  # midline to the centre of the facet joint below
    facet_angle: float  # deg, joint below, from the sagittal plane
    disc_below: float  # height of the disc below

    def scaled(self, body: float, posterior: float, disc: float) -> LevelDims:
        """Body and canal lengths x ``body``, posterior elements x ``posterior``, disc x
        ``disc``; angles unchanged."""
        factors = dict.fromkeys(BODY_LENGTHS, body) | dict.fromkeys(POSTERIOR_LENGTHS, posterior)
        factors["disc_below"] = disc
        return replace(self, **{k: getattr(self, k) * f for k, f in factors.items()})


#: ``LevelDims`` fields that scale with the body, and with the posterior elements.
BODY_LENGTHS = ("body_half_width", "body_half_depth", "body_half_height", "canal_half_width",
                "canal_half_depth", "pedicle_width", "pedicle_height")  # fmt: skip
POSTERIOR_LENGTHS = ("tp_half_span", "spinous_length", "spinous_height", "lamina_thickness",
                     "facet_half_distance")  # fmt: skip


#: Per-level dimensions at scale 1 (means of adult series; docs/anatomy.md cites them).
LEVEL_DIMS: dict[str, LevelDims] = {
    "T12": LevelDims(19.0, 16.5, 11.5, 9.5, 8.0, 7.0, 15.0, 5.0, 26.0, 30.0, 18.0, 6.0,
                     10.0, 20.0, 7.0),
    "L1": LevelDims(20.5, 18.5, 12.5, 10.5, 8.5, 8.0, 15.0, 8.0, 37.0, 33.0, 21.0, 6.0,
                    9.5, 25.0, 8.0),
    "L2": LevelDims(21.5, 18.0, 13.0, 10.75, 8.5, 8.5, 15.0, 10.0, 41.0, 34.0, 22.0, 6.0,
                    13.0, 30.0, 9.0),
    "L3": LevelDims(22.5, 18.5, 13.25, 11.0, 8.5, 10.0, 15.0, 14.0, 46.0, 34.0, 22.0, 6.0,
                    15.0, 35.0, 10.0),
    "L4": LevelDims(23.5, 18.5, 13.0, 11.5, 8.5, 12.0, 14.0, 18.0, 43.0, 32.0, 20.0, 6.0,
                    19.5, 45.0, 11.0),
    "L5": LevelDims(24.5, 18.5, 12.5, 12.5, 8.5, 15.0, 14.0, 25.0, 45.0, 29.0, 17.0, 6.0,
                    19.5, 50.0, 10.0),
    "S1": LevelDims(25.0, 18.0, 12.0, 12.0, 6.5, 15.0, 14.0, 25.0, 0.0, 14.0, 12.0, 6.0,
                    0.0, 0.0, 0.0),
}  # fmt: skip

_NOTCH = 1.0  # mm, concavity of the body's posterior wall at the midline
_WAIST = 0.05  # body narrower at mid-height by this fraction
_ENDPLATE_CONCAVITY = 1.0  # mm at the endplate centre
_LAMINA_LEAN = 0.2  # a per s: the laminae's lower edges sit posterior of their upper edges
_JOINT_GAP = 2.0  # mm, facet joint space
# How far into the disc space below the laminae's lower edges reach (fraction of the disc
# height): L5's stop at its body, so the L5-S1 interlaminar window is the lumbar spine's
# widest, the one interlaminar access to the canal uses.
_LAMINA_DISC_REACH = {"L5": 0.0}
_LAMINA_DISC_REACH_DEFAULT = 0.2
_FILLET = 2.0  # mm, blend between the parts of one bone


@dataclass
class Vertebra:
    """A placed level: frame (centre, columns l, a, s of ``rot``) in mm, and its dimensions."""

    level: str
    label: int
    centre: np.ndarray  # (3,) mm, world
    rot: np.ndarray  # (3, 3) columns l, a, s in world
    dims: LevelDims
    spinous_deviation: float = 0.0  # mm, lateral offset of the spinous tip
    lamina_extension: float = 0.0  # mm, how much further down the laminae reach

    def to_world(self, q) -> np.ndarray:
        return self.centre + self.rot @ np.asarray(q, dtype=np.float64)

    # Arch landmarks in the vertebra frame (mm), derived from the dimensions.
    @property
    def canal_a(self) -> float:
        d = self.dims
        return -d.body_half_depth + _NOTCH - d.canal_half_depth

    @property
    def canal_back(self) -> float:
        return self.canal_a - self.dims.canal_half_depth

    @property
    def pedicle_s(self) -> float:
        return 0.2 * self.dims.body_half_height + 1.0

    @property
    def junction(self) -> tuple[float, float]:
        """(|l|, a) of the pedicle-lamina junction."""
        d = self.dims
        return d.canal_half_width + d.pedicle_width / 2, self.canal_a - 0.4 * d.canal_half_depth

    @property
    def lamina_top(self) -> float:
        return self.pedicle_s + self.dims.pedicle_height / 2 - 1.0

    @property
    def lamina_bottom(self) -> float:
        d = self.dims
        reach = _LAMINA_DISC_REACH.get(self.level, _LAMINA_DISC_REACH_DEFAULT)
        return -d.body_half_height - reach * d.disc_below - self.lamina_extension

    def lean(self, s):
        """Posterior shift (negative a) of the laminae at height s."""
        return -_LAMINA_LEAN * (self.lamina_top - s)

    @property
    def apex_a(self) -> float:
        """a of the laminae's mid-line at the midline, at the laminae's top."""
        return self.canal_back - self.dims.lamina_thickness / 2 + 1.0

    @property
    def spinous_tip(self) -> tuple[float, float, float]:
        """(l, a, s) of the spinous tip's posterior-most point."""
        d = self.dims
        return self.spinous_deviation, self.canal_back - d.spinous_length, self.spinous_tip_s

    @property
    def spinous_tip_s(self) -> float:
        return -0.2 * self.dims.body_half_height - 1.0


# ----------------------------------------------------------------------------- placement


def place_spine(
    scale: float,
    posterior_scale: float,
    disc_scale: float,
    lordosis: float,
    lordosis_apex: float,
    scoliosis: float,
    axial_rotation: float,
    spine_rotation: float,
    variation: np.ndarray,
) -> list[Vertebra]:
    """Place T12..S1 along a lordotic, scoliotic curve; L4's body centre at the origin. The
    lordosis's apex (the most anterior level, whose endplates face the back) lies
    ``lordosis_apex`` of the way from the L3 to the L4 centre.

    ``variation`` (7, 5), one row per level: relative size changes of the body and of the
    posterior elements, relative change of the disc below, the laminae's extension (mm) and the
    spinous tip's lateral deviation (mm). Lengths in mm, angles in rad, scoliosis in mm."""
    dims = {
        lv: LEVEL_DIMS[lv].scaled(
            scale * (1 + variation[i, 0]),
            scale * posterior_scale * (1 + variation[i, 1]),
            disc_scale * (1 + variation[i, 2]),
        )
        for i, lv in enumerate(LEVELS)
    }
    arc = {"L4": 0.0}
    i4 = LEVELS.index("L4")
    for i in range(i4 - 1, -1, -1):
        lo, up = LEVELS[i + 1], LEVELS[i]
        arc[up] = arc[lo] + dims[lo].body_half_height + dims[up].disc_below
        arc[up] += dims[up].body_half_height
    for i in range(i4 + 1, len(LEVELS)):
        up, lo = LEVELS[i - 1], LEVELS[i]
        arc[lo] = arc[up] - dims[up].body_half_height - dims[up].disc_below
        arc[lo] -= dims[lo].body_half_height
    s_lo, s_hi = arc["S1"], arc["T12"]
    apex = arc["L3"] + lordosis_apex * (arc["L4"] - arc["L3"])
    ds = 0.25
    s_grid = np.arange(s_lo - 60.0, s_hi + 60.0, ds)
    # Curvature growing caudally (the lower segments carry most of the lordosis), scaled so
    # that the L1 and S1 endplates differ by ``lordosis``.
    w = 0.3 + 1.4 * np.clip((arc["L1"] - s_grid) / (arc["L1"] - arc["S1"]), 0, 1)
    inside = (s_grid >= arc["S1"]) & (s_grid <= arc["L1"])
    kappa = w * lordosis / (w[inside].sum() * ds)  # rad per mm
    bend = np.cumsum(kappa) * ds
    phi = -(bend - np.interp(apex, s_grid, bend))
    span = np.clip((s_grid - s_lo) / (s_hi - s_lo), 0, 1)
    x = scoliosis * np.sin(np.pi * span)
    psi = spine_rotation + axial_rotation * np.sin(np.pi * span)
    y = np.cumsum(np.sin(phi)) * ds
    z = np.cumsum(np.cos(phi)) * ds
    k0 = int(np.argmin(np.abs(s_grid)))
    y, z = y - y[k0], z - z[k0]
    dx = np.gradient(x, ds)
    out = []
    for i, lv in enumerate(LEVELS):
        k = int(np.argmin(np.abs(s_grid - arc[lv])))
        t = np.array([dx[k], np.sin(phi[k]), np.cos(phi[k])])
        s_ax = t / np.linalg.norm(t)
        a0 = np.array([0.0, 1.0, 0.0]) - s_ax[1] * s_ax
        a0 /= np.linalg.norm(a0)
        l0 = np.cross(a0, s_ax)
        c, s = math.cos(psi[k]), math.sin(psi[k])
        l_ax, a_ax = c * l0 + s * a0, -s * l0 + c * a0
        rot = np.stack([l_ax, a_ax, s_ax], 1)
        out.append(
            Vertebra(
                lv,
                L.VERTEBRA_IDS[lv],
                np.array([x[k], y[k], z[k]]),
                rot,
                dims[lv],
                float(variation[i, 4]),
                float(variation[i, 3]),
            )
        )
    return out


# ----------------------------------------------------------------------------- parts


@dataclass
class Part:
    """An SDF ``fn(u, v, w)`` (mm) in the frame (``centre``, columns of ``rot``), non-positive
    only inside the box ``lo``-``hi`` of that frame."""

    centre: np.ndarray
    rot: np.ndarray
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    fn: Callable[[Tensor, Tensor, Tensor], Tensor]

    def world_box(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.asarray(self.lo) - margin, np.asarray(self.hi) + margin
        corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                            for c in (lo[2], hi[2])])  # fmt: skip
        world = self.centre + corners @ self.rot.T
        return world.min(0), world.max(0)


def _in(v: Vertebra, lo, hi, fn) -> Part:
    return Part(v.centre, v.rot, tuple(lo), tuple(hi), fn)


def body_section(l: Tensor, a: Tensor, hw: float, hd: float) -> Tensor:
    """Kidney-shaped cross-section of a vertebral body (or disc): superellipse, posterior wall
    concave by ``_NOTCH`` at the midline."""
    d = superellipse2(l, a, hw, hd, 3.0)
    notch = ellipse2(l, a + hd + 7.0 - _NOTCH, 0.55 * hw, 7.0)
    return smooth_subtract(d, notch, 2.0)


def _body(v: Vertebra) -> Part:
    d = v.dims
    bw, bd, bh = d.body_half_width, d.body_half_depth, d.body_half_height

    def fn(l, a, s):
        waist = 1.0 - _WAIST * (1.0 - (s / bh) ** 2).clamp_min(0)
        sec = body_section(l / waist, a, bw - 1.5, bd - 1.5) * waist
        r2 = (l / bw) ** 2 + (a / bd) ** 2
        top = bh - 1.5 - _ENDPLATE_CONCAVITY * (1.0 - r2).clamp_min(0)
        qs = s.abs() - top
        out = torch.sqrt(sec.clamp_min(0) ** 2 + qs.clamp_min(0) ** 2)
        return out + torch.maximum(sec, qs).clamp_max(0) - 1.5

    return _in(v, (-bw, -bd, -bh), (bw, bd, bh), fn)


def body_centroid(v: Vertebra, step: float = 0.5) -> np.ndarray:
    """(3,) mm, world: the centroid of the drawn vertebral body (the kidney-shaped section puts
    it a little anterior of the frame's origin)."""
    part = _body(v)
    axes = [torch.arange(lo + step / 2, hi, step, dtype=torch.float64)
            for lo, hi in zip(part.lo, part.hi, strict=True)]  # fmt: skip
    l, a, s = torch.meshgrid(*axes, indexing="ij")
    inside = part.fn(l, a, s) < 0
    q = torch.stack([l[inside], a[inside], s[inside]], 1).mean(0).numpy()
    return v.to_world(q)


def _pedicles(v: Vertebra) -> list[Part]:
    d = v.dims
    th = math.radians(d.pedicle_angle)
    sn, cs = math.sin(th), math.cos(th)
    half = (d.canal_half_depth + 7.0) / cs
    parts = []
    for side in (1.0, -1.0):
        lc = side * (d.canal_half_width + d.pedicle_width / 2)

        def fn(l, a, s, side=side, lc=lc):
            ul, ua = l - lc, a - v.canal_a
            u = ul * (-side * sn) + ua * cs  # along the pedicle axis, anterior positive
            w = ul * cs + ua * (side * sn)
            sec = ellipse2(w, s - v.pedicle_s, d.pedicle_width / 2, d.pedicle_height / 2)
            qu = u.abs() - half
            out = torch.sqrt(sec.clamp_min(0) ** 2 + qu.clamp_min(0) ** 2)
            return out + torch.maximum(sec, qu).clamp_max(0)

        r = half + d.pedicle_width
        lo = (lc - r, v.canal_a - r, v.pedicle_s - d.pedicle_height / 2)
        hi = (lc + r, v.canal_a + r, v.pedicle_s + d.pedicle_height / 2)
        parts.append(_in(v, lo, hi, fn))
    return parts


def _laminae(v: Vertebra) -> Part:
    """Both laminae, from the pedicle-lamina junctions to the midline apex, leaning back."""
    d = v.dims
    lj, aj = v.junction
    top, bot = v.lamina_top, v.lamina_bottom
    rad = d.lamina_thickness / 2
    mid, half = (top + bot) / 2, (top - bot) / 2

    def fn(l, a, s):
        a0 = a - v.lean(s)
        d2 = torch.minimum(
            segment2(l, a0, (lj, aj), (0.0, v.apex_a)), segment2(l, a0, (-lj, aj), (0.0, v.apex_a))
        )
        qs = (s - mid).abs() - half
        d2 = d2 - rad
        out = torch.sqrt(d2.clamp_min(0) ** 2 + qs.clamp_min(0) ** 2)
        return out + torch.maximum(d2, qs).clamp_max(0)

    a_lo = min(aj, v.apex_a) + v.lean(bot) - rad
    return _in(v, (-lj - rad, a_lo, bot), (lj + rad, max(aj, v.apex_a) + rad, top), fn)


def flavum(v: Vertebra, below: Vertebra, thickness: float = 3.5) -> Part:
    """The ligamentum flavum between ``v``'s laminae and those of the level below: a plate on
    the laminae's front (canal) side, following their V and lean, from inside v's laminae down
    into the next level's."""
    d = v.dims
    lj, aj = v.junction
    shift = d.lamina_thickness / 2 + thickness / 2 - 0.5  # onto the laminae's front face
    top = v.lamina_bottom + 6.0
    nxt = below.to_world((0.0, below.apex_a, below.lamina_top - 4.0))
    bot = float((nxt - v.centre) @ v.rot[:, 2])
    mid, half = (top + bot) / 2, (top - bot) / 2
    lf = 0.9 * lj

    def fn(l, a, s):
        a0 = a - v.lean(s) - shift
        d2 = (
            torch.minimum(
                segment2(l, a0, (lf, aj), (0.0, v.apex_a)),
                segment2(l, a0, (-lf, aj), (0.0, v.apex_a)),
            )
            - thickness / 2
        )
        qs = (s - mid).abs() - half
        out = torch.sqrt(d2.clamp_min(0) ** 2 + qs.clamp_min(0) ** 2)
        return out + torch.maximum(d2, qs).clamp_max(0)

    a_lo = min(aj, v.apex_a) + v.lean(bot) + shift - thickness
    a_hi = max(aj, v.apex_a) + shift + thickness
    return _in(v, (-lf - thickness, a_lo, bot), (lf + thickness, a_hi, top), fn)


def _spinous(v: Vertebra) -> Part:
    """Sagittal plate from the laminae's apex line to a club-shaped tip (a disc of the tip's
    height in the sagittal plane), thicker toward the tip."""
    d = v.dims
    half_h = d.spinous_height / 2
    rho = min(5.0, half_h)  # corner radius of the tip
    s_t = v.spinous_tip_s
    a_tip = v.canal_back - d.spinous_length
    s0, s1 = v.lamina_top - 3.0, v.lamina_bottom + 4.0
    ends = ((a_tip + rho, s_t + half_h - rho), (a_tip + rho, s_t - half_h + rho))
    poly = [
        (v.apex_a + 1.0 + v.lean(s0), s0),
        (a_tip + rho, s_t + half_h),
        (a_tip + rho, s_t - half_h),
        (v.apex_a + 1.0 + v.lean(s1), s1),
    ]
    a_base = v.apex_a + v.lean(s_t)
    dev = v.spinous_deviation

    def fn(l, a, s):
        frac = ((a_base - a) / (a_base - a_tip)).clamp(0, 1)
        t = 2.75 + 2.5 * frac**2  # half-thickness: 5.5 mm at the base, 10.5 mm at the tip
        tip = segment2(a, s, ends[0], ends[1]) - rho
        d2 = torch.minimum(polygon2(a, s, poly), tip)
        ql = (l - dev * frac).abs() - t
        out = torch.sqrt(d2.clamp_min(0) ** 2 + ql.clamp_min(0) ** 2)
        return out + torch.maximum(d2, ql).clamp_max(0)

    a_hi = max(q[0] for q in poly)
    return _in(
        v,
        (-abs(dev) - 6.0, a_tip, min(s1, s_t - half_h)),
        (abs(dev) + 6.0, a_hi, max(s0, s_t + half_h)),
        fn,
    )


def _transverse_processes(v: Vertebra) -> list[Part]:
    d = v.dims
    if d.tp_half_span <= 0:
        return []
    lj, aj = v.junction
    stout = v.level == "L5"
    th = 3.5 if stout else 2.5  # half AP thickness
    h_root, h_tip = (8.0, 6.5) if stout else (7.0, 5.5)  # half cranio-caudal height
    root_l, tip_l = lj + 0.5, d.tp_half_span - th
    root_a, tip_a = aj - 1.5, aj - 7.0
    sp = 0.1 * d.body_half_height  # at the pedicles' lower half, level with the body centre
    parts = []
    for side in (1.0, -1.0):
        r0, r1 = (side * root_l, root_a), (side * tip_l, tip_a)

        def fn(l, a, s, side=side, r0=r0, r1=r1):
            t = ((side * l - root_l) / (tip_l - root_l)).clamp(0, 1)
            d2 = segment2(l, a, r0, r1) - th
            qs = (s - sp).abs() - (h_root + (h_tip - h_root) * t)
            out = torch.sqrt(d2.clamp_min(0) ** 2 + qs.clamp_min(0) ** 2)
            return out + torch.maximum(d2, qs).clamp_max(0)

        lo_l, hi_l = sorted((side * (root_l - th), side * (tip_l + th)))
        parts.append(_in(v, (lo_l, tip_a - th, sp - h_root), (hi_l, root_a + th, sp + h_root), fn))
    return parts


@dataclass(frozen=True)
class FacetJoint:
    """A facet joint between ``upper`` and ``lower`` on one side, in the lower level's frame:
    centre (mm, world), axes (columns: t along the joint line, anteromedial; n its normal,
    posteromedial, out of the superior articular process; s)."""

    centre: np.ndarray
    axes: np.ndarray
    side: float


def facet_joint(upper: Vertebra, lower: Vertebra, side: float) -> FacetJoint:
    d = upper.dims
    beta = math.radians(d.facet_angle)
    lj, aj = lower.junction
    s_j = lower.dims.body_half_height + 0.35 * d.disc_below + 1.0
    c = lower.to_world((side * d.facet_half_distance, aj - 2.0, s_j))
    t = np.array([-side * math.sin(beta), math.cos(beta), 0.0])
    n = np.array([-side * math.cos(beta), -math.sin(beta), 0.0])
    axes = lower.rot @ np.stack([t, n, np.array([0.0, 0.0, 1.0])], 1)
    return FacetJoint(c, axes, side)


_SAP = (6.5, 2.75)  # half width along the joint, half thickness
_IAP = (7.0, 3.0)
_FACET_SLOPE = 0.5  # s per u: the articular processes' free ends slope along the joint


def _superior_articular(v: Vertebra, j: FacetJoint) -> list[Part]:
    """The superior articular process of ``v`` (the lower level of joint ``j``): a plate behind
    the joint's anterolateral side, rising from the pedicle-lamina junction, and its root."""
    off = _JOINT_GAP / 2 + _SAP[1]
    c = j.centre - off * j.axes[:, 1]
    # Its lower end reaches down to the pedicle level of v.
    s_j = (j.centre - v.centre) @ v.rot[:, 2]
    bottom = v.pedicle_s - 1.0 - s_j
    top = 5.0
    mid = (top + bottom) / 2
    half = (_SAP[0], _SAP[1], (top - bottom) / 2)
    centre = c + mid * j.axes[:, 2]
    # The tip slopes down toward the anteromedial end (+u), clear of the lamina above.
    k = _FACET_SLOPE

    def sap(u, n, s):
        return torch.maximum(round_box(u, n, s, half, 1.5), s - half[2] + k * (u + half[0]))

    plate = Part(centre, j.axes, tuple(-h for h in half), half, sap)
    lj, aj = v.junction
    root = v.to_world((j.side * (lj - 1.0), aj - 1.0, v.pedicle_s))
    return [plate, _capsule_part(root, centre, 4.0)]


def _inferior_articular(v: Vertebra, j: FacetJoint) -> list[Part]:
    """The inferior articular process of ``v`` (the upper level of joint ``j``): a plate on the
    joint's posteromedial side, hanging from the laminae's inferolateral corner."""
    off = _JOINT_GAP / 2 + _IAP[1]
    c = j.centre + off * j.axes[:, 1]
    half = (_IAP[0], _IAP[1], 8.0)
    centre = c - (2.0 + v.lamina_extension) * j.axes[:, 2]  # hangs as low as the laminae
    k = _FACET_SLOPE

    def iap(u, n, s):  # its lower end rises toward the anteromedial end (+u)
        return torch.maximum(round_box(u, n, s, half, 1.5), -s - half[2] + k * (u + half[0]))

    plate = Part(centre, j.axes, tuple(-h for h in half), half, iap)
    lj, aj = v.junction
    s_c = v.lamina_bottom + 4.0
    l_c = lj - 3.0
    a_c = aj + (v.apex_a - aj) * (1 - l_c / lj) + v.lean(s_c)
    corner = v.to_world((j.side * l_c, a_c, s_c))
    return [plate, _capsule_part(corner, centre, 4.0)]


def _capsule_part(a: np.ndarray, b: np.ndarray, r: float) -> Part:
    """A capsule in world coordinates (mm)."""
    lo, hi = np.minimum(a, b) - r, np.maximum(a, b) + r
    return Part(np.zeros(3), np.eye(3), tuple(lo), tuple(hi),
                lambda x, y, z: capsule(x, y, z, tuple(a), tuple(b), r))  # fmt: skip


def _sacral_wings(v: Vertebra) -> list[Part]:
    """S1's alae: wedges from the body and pedicles to the sacroiliac joints, and its dorsal
    plate with the first median-crest tubercle."""
    d = v.dims
    bh = d.body_half_height
    parts = []
    for side in (1.0, -1.0):
        # From beside the body back to the sacroiliac joint; the ala's centre lies behind the
        # body's, level with the canal (its dorsal surface carries the lateral sacral crest).
        half = (25.0, 17.0, bh + 3.0)
        c = (side * 30.0, v.canal_a + 4.0, -3.0)

        def fn(l, a, s, c=c, half=half):
            return round_box(l - c[0], a - c[1], s - c[2], half, 5.0)

        parts.append(_in(v, np.subtract(c, half), np.add(c, half), fn))
    return parts


def _sacral_dorsum(v: Vertebra, half_width: float, half_height: float, crest: float) -> list[Part]:
    """Dorsal plate (fused laminae) behind the canal and the median crest on it."""
    a_back = v.canal_back
    t = 2.5
    plate_half = (half_width, t, half_height)
    pc = (0.0, a_back - t + 1.0, 0.0)
    parts = [
        _in(v, np.subtract(pc, plate_half), np.add(pc, plate_half),
            lambda l, a, s: round_box(l - pc[0], a - pc[1], s - pc[2], plate_half, 2.0)),
    ]  # fmt: skip
    if crest > 0:
        ch = (3.0, crest / 2 + 1.0, max(half_height - 3.0, 2.0))
        cc = (0.0, a_back - 2 * t - crest / 2 + 1.0, 0.0)
        parts.append(
            _in(v, np.subtract(cc, ch), np.add(cc, ch),
                lambda l, a, s: round_box(l - cc[0], a - cc[1], s - cc[2], ch, 2.5))
        )  # fmt: skip
    return parts


def vertebra_parts(v: Vertebra, above: Vertebra | None, below: Vertebra | None) -> list[Part]:
    """Every part of one level's bone (not the canal, which is carved afterwards)."""
    parts = [_body(v), *_pedicles(v)]
    if v.level == "S1":
        parts += _sacral_wings(v)
        parts += _sacral_dorsum(v, v.dims.canal_half_width + 6.0, v.dims.body_half_height, 7.0)
    else:
        parts += [_laminae(v), _spinous(v), *_transverse_processes(v)]
        if below is not None:
            for side in (1.0, -1.0):
                parts += _inferior_articular(v, facet_joint(v, below, side))
    # Superior articular processes face the level above (T12's face a T11 that is not drawn).
    up = above if above is not None else v
    for side in (1.0, -1.0):
        j = facet_joint(up, v, side) if above is not None else _own_joint(v, side)
        parts += _superior_articular(v, j)
    return parts


def _own_joint(v: Vertebra, side: float) -> FacetJoint:
    """The joint above a level with no drawn level above (T12): its own facet geometry."""
    ghost = Vertebra(v.level, v.label, v.centre, v.rot, v.dims)
    return facet_joint(ghost, v, side)


# ----------------------------------------------------------------------------- sacrum, pelvis


#: Sacral segments below S1: (half-height, body half-width, body half-depth, canal half-width,
#: canal half-depth, dorsal half-width, lateral-mass half-width, crest height), mm.
_SACRAL = (
    (11.0, 20.0, 13.0, 9.0, 4.0, 22.0, 42.0, 6.0),
    (9.0, 15.0, 11.0, 7.0, 3.5, 18.0, 30.0, 5.0),
    (7.0, 11.0, 9.0, 6.0, 3.0, 13.0, 18.0, 3.0),
)
_SACRAL_BEND = math.radians(12.0)  # per segment, anteriorly (the sacrum's kyphosis)


def sacral_segments(s1: Vertebra, scale: float) -> list[Vertebra]:
    """Frames and dimensions of S2-S4, continuing below S1 and bending anteriorly."""
    out = []
    c, rot = s1.centre.copy(), s1.rot.copy()
    prev_h = s1.dims.body_half_height
    for k, (hh, bw, bd, cw, cd, _dw, _lw, _cr) in enumerate(_SACRAL):
        th = _SACRAL_BEND
        cs, sn = math.cos(th), math.sin(th)
        a_ax, s_ax = rot[:, 1], rot[:, 2]
        step = -(prev_h + hh * scale + 1.0)
        mid_s = cs * s_ax - sn * a_ax * 0.5  # half the bend before, half after
        c = c + step * mid_s / np.linalg.norm(mid_s)
        new_s = cs * s_ax - sn * a_ax
        new_a = sn * s_ax + cs * a_ax
        rot = np.stack([rot[:, 0], new_a, new_s], 1)
        dims = replace(
            s1.dims,
            body_half_width=bw * scale,
            body_half_depth=bd * scale,
            body_half_height=hh * scale,
            canal_half_width=cw * scale,
            canal_half_depth=cd * scale,
        )
        out.append(Vertebra(f"S{k + 2}", L.LABEL_IDS["sacrum"], c.copy(), rot.copy(), dims))
        prev_h = hh * scale
    return out


def sacral_parts(seg: Vertebra, k: int, scale: float) -> list[Part]:
    """Body, dorsal plate, median crest and lateral masses of sacral segment S(k + 2)."""
    hh, bw, bd, _cw, _cd, dw, lw, crest = _SACRAL[k]
    d = seg.dims
    hh, dw, lw, crest = hh * scale + 1.0, dw * scale, lw * scale, crest * scale

    def body(l, a, s):
        sec = superellipse2(l, a, d.body_half_width, d.body_half_depth, 2.4)
        qs = s.abs() - hh
        out = torch.sqrt(sec.clamp_min(0) ** 2 + qs.clamp_min(0) ** 2)
        return out + torch.maximum(sec, qs).clamp_max(0)

    bwd, bdd = d.body_half_width, d.body_half_depth
    parts = [_in(seg, (-bwd, -bdd, -hh), (bwd, bdd, hh), body)]
    parts += _sacral_dorsum(seg, dw, hh, crest)
    mass = (lw / 2, (bdd + abs(seg.canal_back)) / 2, hh)
    for side in (1.0, -1.0):
        mc = (side * lw / 2, (bdd + seg.canal_back) / 2, 0.0)
        parts.append(
            _in(seg, np.subtract(mc, mass), np.add(mc, mass),
                lambda l, a, s, mc=mc: round_box(l - mc[0], a - mc[1], s - mc[2], mass, 4.0))
        )  # fmt: skip
    return parts


def ilium_parts(l5: Vertebra, l4: Vertebra, side: float, crest_level: float) -> list[Part]:
    """One iliac bone in the L5 frame (the pelvis's orientation): a curved wing whose crest
    rises from the posterior superior iliac spine (PSIS, beside the upper sacrum) to a summit
    ``crest_level`` of the way from the L5 centre up to the L4 centre, and the thick posterior
    ilium between the sacroiliac joint and the PSIS."""
    s_sum = crest_level * float((l4.centre - l5.centre) @ l5.rot[:, 2])
    s_psis = -12.0
    # Wing mid-surface in the (l, a) plane: an arc through the PSIS end (45, -60) and the
    # lateral end (125, 5), concave anteromedially (the iliac fossa).
    cen, rad = (17.0, 56.4), 120.0
    th0 = math.atan2(-60.0 - cen[1], 45.0 - cen[0])
    th1 = math.atan2(5.0 - cen[1], 125.0 - cen[0])
    t_half = 3.0

    def wing(l, a, s):
        ls = side * l
        ang = torch.atan2(a - cen[1], ls - cen[0])
        t = ((ang - th0) / (th1 - th0)).clamp(0, 1)
        shell = (torch.sqrt((ls - cen[0]) ** 2 + (a - cen[1]) ** 2) - rad).abs() - t_half
        # ends of the arc
        ends = torch.maximum(th0 - ang, ang - th1) * rad
        d2 = torch.maximum(shell, ends)
        rise = torch.where(t < 0.75, 1 - (1 - t / 0.75) ** 2, 1 - 3.0 * (t - 0.75) ** 2)
        top = s_psis + (s_sum - s_psis) * rise
        return torch.maximum(d2, s - top)

    lo = (min(side * 40.0, side * 135.0), -70.0, -170.0)
    hi = (max(side * 40.0, side * 135.0), 15.0, s_sum + 2.0)
    parts = [_in(l5, lo, hi, wing)]
    # Posterior ilium: from the sacroiliac joint back to the PSIS.
    si = l5.to_world((side * 45.0, -32.0, -35.0))
    psis = l5.to_world((side * 46.0, -68.0, -28.0))
    crest = l5.to_world((side * 47.0, -58.0, s_psis - 4.0))
    parts.append(_capsule_part(si, psis, 9.0))
    parts.append(_capsule_part(psis, crest, 6.0))
    return parts


def canal_sdf(v: Vertebra, l: Tensor, a: Tensor, s: Tensor, extra: float = 12.0) -> Tensor:
    """The vertebral canal of ``v`` (an elliptic cylinder along s, reaching ``extra`` mm past
    the endplates)."""
    d = v.dims
    sec = ellipse2(l, a - v.canal_a, d.canal_half_width, d.canal_half_depth)
    qs = s.abs() - (d.body_half_height + extra)
    out = torch.sqrt(sec.clamp_min(0) ** 2 + qs.clamp_min(0) ** 2)
    return out + torch.maximum(sec, qs).clamp_max(0)


def local_coords(centre: np.ndarray, rot: np.ndarray, x: Tensor, y: Tensor, z: Tensor):
    """World (mm) -> the frame (centre, columns of rot): (u, v, w)."""
    dx, dy, dz = x - float(centre[0]), y - float(centre[1]), z - float(centre[2])
    r = rot
    return (
        dx * float(r[0, 0]) + dy * float(r[1, 0]) + dz * float(r[2, 0]),
        dx * float(r[0, 1]) + dy * float(r[1, 1]) + dz * float(r[2, 1]),
        dx * float(r[0, 2]) + dy * float(r[1, 2]) + dz * float(r[2, 2]),
    )
