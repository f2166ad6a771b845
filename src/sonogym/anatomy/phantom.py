"""Procedural lumbar phantom: a prone adult torso with T12-S1, sacrum and pelvis, drawn from
signed distances.

``make_phantom(seed, params)`` returns a :class:`~sonogym.anatomy.patient.Patient` whose label
map uses TotalSegmentator v2 ids (plus project ids >= 118) and whose CT is in Hounsfield units
with partial-volume edges and CT noise. Bones come from ``phantom_spine`` (each vertebra built
from a kidney-shaped body, pedicles, a continuous arch of laminae and spinous process, facet
joints and transverse processes; sacrum with its median crest; iliac crests beside L4-L5). Over
them lie the paraspinal muscles (autochthon) under the thoracolumbar fascia, convex lobes in
fat-lined fascial envelopes that meet the midline down at the spinous tips with fat in the cleft
between them, the supra- and interspinous ligaments in the midline, the ligamentum flavum behind
the canal, subcutaneous fat thicker on the flanks and over the midline furrow, and skin.
Dimensions and their spread follow published adult morphometry (docs/anatomy.md).

The generator is a pipeline of layer builders, each painting one kind of tissue over what the
earlier ones left (labels are overwritten, CT blended by partial volume), so their order is
part of the anatomy:

1. ``_place_body``: the vertebrae and sacrum, and the anchor lines of the back along them;
2. ``_lay_out``: the paramedian skin line and the canvas (air) around the trunk;
3. ``_paint_trunk``: skin, generic soft tissue, the paraspinal muscles in their fascia, and
   the subcutaneous fat, slab by slab;
4. ``_paint_spinous_ligaments``: supra- and interspinous ligaments under the fat;
5. ``_paint_organs``, ``_paint_iliopsoas``: liver, kidneys and psoas, only where generic soft
   tissue is left;
6. ``_paint_great_vessels``: aorta, vena cava and iliac vessels;
7. ``_paint_discs``, ``_paint_canals`` (canals, then the cord), ``_paint_flavum``;
8. ``_paint_vertebrae``, ``_paint_pelvis`` (ilia, then the sacrum), ``_paint_ribs``: bone over
   the soft tissue, each vertebra carved around its own canal;
9. ``_cover_bone``: bone that reaches the back's surface becomes skin and fat;
10. ``_noisy_ct``: CT noise, rounded to integer HU.

The layers read a frozen ``_Context``: the resolved parameters, the placed bones, the anchor
lines, the skin line and the canvas they paint.

Variability comes from named parameters (``PhantomParams``); any left ``None`` is drawn from the
seed, and per-level size changes and spinous-tip deviations are drawn from the seed as well
(their spread is ``level_spread`` and ``spinous_spread``). The same seed and params give the
same volumes bit for bit.

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
from sonogym.anatomy import phantom_spine as S
from sonogym.anatomy.cache import cached_patient
from sonogym.anatomy.patient import Patient
from sonogym.anatomy.sdf import (
    capsule,
    ellipse2,
    ellipsoid,
    smooth_union,
    superellipse2,
)

#: Bump when the generator's output changes, so stale cache entries are not reused.
GENERATOR_VERSION = 10

# ----------------------------------------------------------------------------- parameters

#: Drawn parameters: name -> (low, high). Drawn in this order from the seed, each always drawn
#: (even when given) so fixing one parameter leaves the others' draws unchanged.
_SAMPLED: dict[str, tuple[float, float]] = {
    "torso_half_width": (0.145, 0.190),  # m
    "torso_depth": (0.200, 0.270),  # m
    "fat_thickness": (0.003, 0.022),  # m
    "muscle_bulk": (0.85, 1.20),  # scale
    "vertebra_scale": (0.92, 1.14),  # scale
    "lordosis": (0.45, 0.85),  # rad, L1 vs S1 endplates (prone)
    "scoliosis": (-0.006, 0.006),  # m, peak lateral offset
    "axial_rotation": (-0.05, 0.05),  # rad, peak axial rotation
    "cancellous_hu": (150.0, 260.0),  # HU
    "posterior_scale": (0.94, 1.08),  # scale
    "disc_scale": (0.80, 1.20),  # scale
    "spine_rotation": (-0.08, 0.08),  # rad
    "fat_lateral": (0.2, 1.5),  # unitless
    "muscle_bulge": (0.0, 0.016),  # m
    "midline_furrow": (0.0, 0.8),  # unitless
    "supraspinous": (0.002, 0.006),  # m
    "caudal_depth": (0.0, 0.010),  # m
    "crest_level": (0.3, 1.1),  # unitless
    "lordosis_apex": (0.0, 1.0),  # unitless
    "back_curvature": (0.3, 0.9),  # unitless
    "gluteal": (0.0, 0.040),  # m
    "trunk_roll": (-0.12, 0.12),  # rad
    "muscle_hu": (10.0, 50.0),  # HU (drawn last: the earlier draws of a seed stay as they were)
    "multifidus_width": (0.40, 0.60),  # unitless, share of the paraspinal width
    "muscle_cleft": (0.002, 0.012),  # m
}


@dataclass(frozen=True)
class PhantomParams:
    """Phantom parameters. ``None`` fields are drawn from the seed (ranges in ``_SAMPLED``)."""

    spacing: float = 0.001  # m, isotropic voxel size (0.0005-0.002)
    torso_half_width: float | None = None  # m, half the back's width
    torso_depth: float | None = None  # m, back-to-belly
    fat_thickness: float | None = None  # m, subcutaneous fat beside the spine, above L3
    muscle_bulk: float | None = None  # unitless scale of the paraspinal and psoas muscles
    vertebra_scale: float | None = None  # unitless scale of every vertebra
    lordosis: float | None = None  # rad, angle between the L1 and S1 endplates
    scoliosis: float | None = None  # m, peak lateral deviation of the spine (sign = side)
    axial_rotation: float | None = None  # rad, peak axial rotation of the vertebrae (mid-spine)
    cancellous_hu: float | None = None  # HU of cancellous bone (bone density)
    posterior_scale: float | None = None  # unitless, posterior elements relative to the bodies
    disc_scale: float | None = None  # unitless scale of the disc heights (level spacing)
    spine_rotation: float | None = None  # rad, axial rotation of the whole spine in the trunk
    fat_lateral: float | None = None  # unitless, extra fat 80 mm from the midline (x thickness)
    muscle_bulge: float | None = None  # m, paraspinal muscles' bulge behind the spinous tips
    midline_furrow: float | None = None  # unitless 0-1, share of that furrow the skin shows
    supraspinous: float | None = None  # m, soft tissue (ligament) over the spinous tips
    caudal_depth: float | None = None  # m, extra soft tissue over L5 relative to L1
    crest_level: float | None = None  # unitless, iliac crest summit from L5 (0) to L4 (1) centre
    lordosis_apex: float | None = None  # unitless, apex of the lordosis from L3 (0) to L4 (1)
    back_curvature: float | None = None  # unitless, share of the lordotic curve the skin follows
    gluteal: float | None = None  # m, fat behind the sacrum rising from L3 (the buttocks' slope)
    trunk_roll: float | None = None  # rad, the patient rolled (trunk and spine) on the table
    muscle_hu: float | None = None  # HU of the paraspinal muscles (lower: fatty infiltration)
    multifidus_width: float | None = None  # unitless, multifidus' share of the paraspinal width
    muscle_cleft: float | None = None  # m, width of the fat-filled cleft over the spinous tips
    level_spread: float = 0.04  # unitless, std of the per-level size changes (drawn per level)
    disc_spread: float = 0.12  # unitless, std of the per-level disc height changes
    lamina_spread: float = 0.0025  # m, std of how far down each level's laminae reach
    spinous_spread: float = 0.0025  # m, std of the spinous tips' lateral deviation (per level)
    cortical_hu: float = 1400.0  # HU of cortical bone
    ct_noise_hu: float = 15.0  # HU, std of Gaussian CT noise
    fov_inferior: float = 0.125  # m, field of view below the L4 centre
    fov_superior: float = 0.165  # m, field of view above the L4 centre (T12 included)

    def __post_init__(self) -> None:
        if not 0.0005 <= self.spacing <= 0.002:
            raise ValueError(
                f"phantom spacing {self.spacing} m is outside 0.0005-0.002 m (0.5-2.0 mm)"
            )
        if self.fov_inferior < 0.12 or self.fov_superior < 0.12:
            raise ValueError("the field of view must cover at least 0.12 m either side of L4")
        spreads = {
            "level_spread": (self.level_spread, 0.1),
            "disc_spread": (self.disc_spread, 0.25),
            "lamina_spread": (self.lamina_spread, 0.004),
            "spinous_spread": (self.spinous_spread, 0.004),
        }
        for name, (value, top) in spreads.items():
            if not 0 <= value <= top:
                raise ValueError(f"{name} {value} is outside 0-{top} (a standard deviation)")

    def resolved(self, seed: int) -> PhantomParams:
        """A copy with every ``None`` field drawn from ``seed``."""
        rng = np.random.default_rng(seed)
        draws = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in _SAMPLED.items()}
        return dataclasses.replace(
            self, **{k: v for k, v in draws.items() if getattr(self, k) is None}
        )


def _level_variation(seed: int, p: PhantomParams) -> np.ndarray:
    """(7, 5) per-level variation, T12..S1, from its own stream of the seed (each draw within
    +-2 std): relative body and posterior-element size (std ``level_spread``), relative disc
    height (``disc_spread``), laminae extension (mm, ``lamina_spread``) and spinous-tip lateral
    deviation (mm, ``spinous_spread``)."""
    rng = np.random.default_rng([int(seed), 7])
    z = np.clip(rng.standard_normal((len(S.LEVELS), 5)), -2, 2)
    std = [p.level_spread, p.level_spread, p.disc_spread, p.lamina_spread * 1e3,
           p.spinous_spread * 1e3]  # fmt: skip
    return z * np.array(std)


# Tissue HU: typical CT values of each tissue (docs/anatomy.md).
_HU = {
    "air": -1000.0,
    "soft": 20.0,
    "fat": -100.0,
    "skin": 30.0,
    "muscle": 50.0,
    "ligament": 75.0,
    "liver": 55.0,
    "kidney": 30.0,
    "blood": 40.0,
    "disc": 80.0,
    "csf": 15.0,
    "cord": 35.0,
}
_SKIN_MM = 2.5
_MIN_COVER_MM = 2.0  # fat between the skin and a bone that reaches the back's surface
_FASCIA_MM = 1.5  # thoracolumbar fascia over the paraspinal muscles
_TIP_HALF_MM = 5.0  # half the spinous tip's width: the cleft over it is at least this wide
_LOBE_MM = 6.0  # how far the muscle lobes rise behind the spinous tips, beyond their cover
_ENVELOPE_MM = 1.5  # the paraspinal muscles' fascial envelope, with the fat plane lining it
_ENVELOPE_HU = -60.0  # a thin fascia in fat: on CT only the fat shows
_FURROW_SIGMA = 14.0  # mm, half-width scale of the midline furrow between the muscle bulges


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
        occ = sdf.mul(-1.0 / self.h).add_(0.5).clamp_(0, 1)
        ct = self.ct[sl]
        ct.addcmul_(occ, torch.sub(hu, ct) if isinstance(hu, torch.Tensor) else ct.neg().add_(hu))
        self.labels[sl].masked_fill_(sdf < 0, label)

    def z_chunks(self, n: int = 24):
        for k0 in range(0, self.shape[2], n):
            yield (slice(None), slice(None), slice(k0, min(k0 + n, self.shape[2])))

    def union(self, parts: list[S.Part]):
        """(index box, SDF there, first part's SDF there) of the fillet-joined parts; each part
        is evaluated only in its own box (plus the fillet), or None if no part is in view."""
        margin = S._FILLET + 2 * self.h
        boxes = [p.world_box(margin) for p in parts]
        sl = self.box(np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0))
        if sl is None:
            return None
        shape = tuple(s.stop - s.start for s in sl)
        acc = torch.full(shape, 1e3)
        first = torch.full(shape, 1e3)
        for k, (part, (lo, hi)) in enumerate(zip(parts, boxes, strict=True)):
            sub = self.box(lo, hi)
            if sub is None:
                continue
            rel = tuple(
                slice(max(a.start, b.start) - b.start, min(a.stop, b.stop) - b.start)
                for a, b in zip(sub, sl, strict=True)
            )
            if any(r.stop <= r.start for r in rel):
                continue
            glob = tuple(
                slice(r.start + b.start, r.stop + b.start) for r, b in zip(rel, sl, strict=True)
            )
            u, v, w = S.local_coords(part.centre, part.rot, *self.coords(glob))
            d = part.fn(u, v, w)
            acc[rel] = smooth_union(acc[rel], d, S._FILLET)
            if k == 0:
                first[rel] = d
        return sl, acc, first

    def paint_bone(self, sl, bone, body, label: int, p: PhantomParams) -> None:
        """Cortical shell (1 mm on the body, 2 mm elsewhere) over cancellous bone."""
        t_cortex = torch.where(body <= bone + 0.5, 1.0, 2.0)
        hu = p.cancellous_hu + (p.cortical_hu - p.cancellous_hu) * (
            (bone + t_cortex) / self.h + 0.5
        ).clamp(0, 1)
        self.paint(sl, bone, label, hu)


def _near(mask: torch.Tensor, reach: int) -> torch.Tensor:
    """Voxels within ``reach`` voxels of ``mask`` along every axis (a cube around each)."""
    x = mask[None, None].to(torch.float32)
    for k in range(3):
        size = [1, 1, 1]
        size[k] = 2 * reach + 1
        pad = [0, 0, 0]
        pad[k] = reach
        x = torch.nn.functional.max_pool3d(x, tuple(size), stride=1, padding=tuple(pad))
    return x[0, 0] > 0


def _cover_bone(cv: _Canvas) -> None:
    """Bone drawn through the back's surface (an iliac crest on a thin, rolled trunk: the
    pelvis turns with the spine, the skin does not) becomes skin and fat, so every bone lies
    under the skin and ``_MIN_COVER_MM`` of fat as it does in a patient."""
    air = cv.labels == 0
    reach = math.ceil((_SKIN_MM + _MIN_COVER_MM) / cv.h)
    bone = torch.isin(cv.labels, torch.tensor(sorted(L.BONE_IDS), dtype=cv.labels.dtype))
    exposed = bone & _near(air, reach)
    if not exposed.any():
        return
    skin = exposed & _near(air, math.ceil(_SKIN_MM / cv.h))
    fat = exposed & ~skin
    cv.labels[skin] = L.SKIN
    cv.ct[skin] = _HU["skin"]
    cv.labels[fat] = L.SUBCUTANEOUS_FAT
    cv.ct[fat] = _HU["fat"]


def _round_rect(u: torch.Tensor, v: torch.Tensor, hu: float, hv, r: float) -> torch.Tensor:
    """2-D rectangle of half-sizes (hu, hv) with corners rounded by r (hv may be a tensor)."""
    qu = u.abs() - (hu - r)
    qv = v.abs() - (hv - r)
    out = torch.sqrt(qu.clamp_min(0) ** 2 + qv.clamp_min(0) ** 2)
    return out + torch.maximum(qu, qv).clamp_max(0) - r


def _interp(zs: np.ndarray, vs: np.ndarray, z: torch.Tensor) -> torch.Tensor:
    """Anchor line (zs, vs) interpolated at grid z (tensor (1, 1, nz)) -> (1, 1, nz)."""
    order = np.argsort(zs)
    out = np.interp(z.flatten().numpy(), zs[order], vs[order])
    return torch.tensor(out, dtype=torch.float32).view(1, 1, -1)


# ----------------------------------------------------------------------------- layer context


@dataclass(frozen=True, eq=False)
class _Body:
    """The resolved parameters, the placed bones and the anchor lines (world mm) along which
    the soft tissue is drawn."""

    p: PhantomParams
    verts: list[S.Vertebra]  # T12..S1
    sacrum: list[S.Vertebra]  # S2..S4
    by: dict[str, S.Vertebra]  # verts by level name
    tips: np.ndarray  # (6, 3) spinous tips, T12..L5
    back_line: np.ndarray  # the midline's posterior bone: spinous tips, then the sacral crest
    apex: np.ndarray  # (6, 3) the laminae's midline apex at each spinous tip's height
    tp_line: np.ndarray  # (6, 3) depth of the transverse processes (pedicle-lamina junction)
    bodies: np.ndarray  # (7, 3) vertebral body centres, T12..S1

    @property
    def psi(self) -> float:
        """rad, the spine's rotation in the trunk (its mid-spine peak aside)."""
        return self.p.spine_rotation + self.p.trunk_roll

    @property
    def z_lo(self) -> float:
        """mm, the field of view's inferior end."""
        return -self.p.fov_inferior * 1e3

    @property
    def z_hi(self) -> float:
        """mm, the field of view's superior end."""
        return self.p.fov_superior * 1e3

    def cover(self, z: torch.Tensor) -> torch.Tensor:
        """Soft tissue (mm) between the fascia and the midline bone, growing caudally."""
        z_l1, z_l5 = self.by["L1"].centre[2], self.by["L5"].centre[2]
        t = ((z_l1 - z) / (z_l1 - z_l5)).clamp(0, 1)
        return self.p.supraspinous * 1e3 + self.p.caudal_depth * 1e3 * t

    def buttock(self, z: torch.Tensor) -> torch.Tensor:
        """Extra fat (mm) rising smoothly from L3 down to S2 (the back's lower slope)."""
        z_l3, z_s2 = self.by["L3"].centre[2], self.sacrum[0].centre[2]
        t = ((z_l3 - z) / (z_l3 - z_s2)).clamp(0, 1)
        return self.p.gluteal * 1e3 * t * t * (3 - 2 * t)

    def body_x(self, zv: float) -> float:
        """x (mm) of the vertebral bodies' line at height ``zv``."""
        return float(np.interp(zv, self.bodies[::-1, 2], self.bodies[::-1, 0]))

    def body_y(self, zv: float) -> float:
        """y (mm) of the vertebral bodies' line at height ``zv``."""
        return float(np.interp(zv, self.bodies[::-1, 2], self.bodies[::-1, 1]))


@dataclass(frozen=True, eq=False)
class _Context(_Body):
    """What the layer builders read, and the canvas they paint in turn."""

    cv: _Canvas
    skin_z: np.ndarray  # mm, heights of the paramedian skin line (1 mm apart)
    skin_y: np.ndarray  # mm, the paramedian skin's y there (the back's posterior-most line)
    hi: np.ndarray  # mm, the field of view's upper corner (cv.lo, on the grid, is the lower)


@dataclass(frozen=True, eq=False)
class _Slab:
    """One z-chunk of the trunk: grid coordinates (mm, broadcast) in the frames its layers are
    drawn in."""

    sl: tuple[slice, slice, slice]
    x: torch.Tensor
    y: torch.Tensor
    z: torch.Tensor
    yp: torch.Tensor  # y of the paramedian skin
    xs: torch.Tensor  # x of the midline bone
    yt: torch.Tensor  # y of the midline bone
    xr: torch.Tensor  # x, y unrolled: the trunk turned back by trunk_roll about the bodies
    yr: torch.Tensor
    xs_r: torch.Tensor  # x of the midline bone, unrolled
    xm: torch.Tensor  # x, y in the spine's rotated frame (the muscles lie on the spine)
    ym: torch.Tensor


# ----------------------------------------------------------------------------- generator


def make_phantom(seed: int = 0, params: PhantomParams | None = None) -> Patient:
    """Build the procedural phantom for ``seed`` (deterministic; no I/O).

    Each layer paints over what the layers before it left, so the order below is part of the
    anatomy (module docstring).
    """
    p = (params or PhantomParams()).resolved(seed)
    ctx = _lay_out(_place_body(seed, p))
    _paint_trunk(ctx)
    _paint_spinous_ligaments(ctx)
    _paint_organs(ctx)
    _paint_iliopsoas(ctx)
    _paint_great_vessels(ctx)
    _paint_discs(ctx)
    _paint_canals(ctx)
    _paint_flavum(ctx)
    _paint_vertebrae(ctx)
    _paint_pelvis(ctx)
    _paint_ribs(ctx)
    _cover_bone(ctx.cv)
    ct = _noisy_ct(ctx, seed)
    return Patient(
        ct=ct,
        labels=ctx.cv.labels,
        affine=_affine(ctx),
        name=f"phantom-{seed}",
        meta=_meta(ctx, seed),
    )


def _place_body(seed: int, p: PhantomParams) -> _Body:
    """Place T12-S1 and the sacrum, and trace the anchor lines of the back along them."""
    verts = S.place_spine(
        p.vertebra_scale, p.posterior_scale, p.disc_scale, p.lordosis, p.lordosis_apex,
        p.scoliosis * 1e3,
        p.axial_rotation, p.spine_rotation + p.trunk_roll, _level_variation(seed, p),
    )  # fmt: skip
    by = {v.level: v for v in verts}
    sacrum = S.sacral_segments(by["S1"], p.vertebra_scale)
    lumbar = [v for v in verts if v.level != "S1"]
    tips = np.array([v.to_world(v.spinous_tip) for v in lumbar])
    crest = [v.to_world((0.0, v.canal_back - 5.0 - 6.0 * p.vertebra_scale, 0.0))
             for v in [by["S1"], *sacrum[:2]]]  # fmt: skip
    return _Body(
        p=p,
        verts=verts,
        sacrum=sacrum,
        by=by,
        tips=tips,
        back_line=np.concatenate([tips, np.array(crest)]),
        apex=np.array([v.to_world((0.0, v.apex_a, v.spinous_tip_s)) for v in lumbar]),
        tp_line=np.array([v.to_world((0.0, v.junction[1], v.pedicle_s)) for v in lumbar]),
        bodies=np.array([v.centre for v in verts]),
    )


def _lay_out(b: _Body) -> _Context:
    """The paramedian skin line over the midline bone, and the canvas that holds the trunk
    around it (air everywhere). First step: every layer paints on this canvas."""
    p = b.p
    h = p.spacing * 1e3
    fat = p.fat_thickness * 1e3
    half_w = p.torso_half_width * 1e3
    depth = p.torso_depth * 1e3
    bulge, furrow = p.muscle_bulge * 1e3, p.midline_furrow
    # Midline skin: above the midline bone by skin, fat (plus the part of the muscle furrow the
    # fat fills), fascia and the ligament cover.
    zz = torch.arange(b.z_lo - 20, b.z_hi + 20, 1.0).view(1, 1, -1)
    y_bone = _interp(b.back_line[:, 2], b.back_line[:, 1], zz)
    # The back's skin follows only part of the lordotic curve of the midline bone (soft tissue
    # fills the hollow): the bone line, pulled toward its straight chord from L1 to L5.
    e1, e5 = (b.by[lv].to_world(b.by[lv].spinous_tip) for lv in ("L1", "L5"))
    chord = e5[1] + (e1[1] - e5[1]) / (e1[2] - e5[2]) * (zz - e5[2])
    flat = (1 - p.back_curvature) * (y_bone - chord).clamp_min(0)
    y_bone_skin = y_bone - flat
    y_skin_mid = y_bone_skin - (_SKIN_MM + fat + b.buttock(zz) + (1 - furrow) * bulge
                                + _FASCIA_MM + b.cover(zz))  # fmt: skip
    y_post = (y_skin_mid - furrow * bulge).flatten().numpy()  # paramedian skin
    zz = zz.flatten().numpy()
    roll = abs(p.trunk_roll)  # a rolled trunk reaches further out at its corners
    side, back = 12.0 + roll * 80.0, 12.0 + roll * half_w
    lo = np.array([-(half_w + side), y_post.min() - back, b.z_lo])
    hi = np.array([half_w + side, y_post.max() + depth + back, b.z_hi])
    lo = np.round(lo / h) * h
    shape = tuple(int(round((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    return _Context(**vars(b), cv=_Canvas(lo, shape, h), skin_z=zz, skin_y=y_post, hi=hi)


def _paint_trunk(ctx: _Context) -> None:
    """Skin, generic soft tissue, subcutaneous fat and the paraspinal muscles in their fascia,
    slab by slab. Runs first, on air: the later layers paint inside the body it outlines."""
    p, cv = ctx.p, ctx.cv
    fat = p.fat_thickness * 1e3
    for sl in cv.z_chunks():
        s = _trunk_slab(ctx, sl)
        torso = _torso_sdf(ctx, s)
        # Skin over the whole body first, then the layers inside it: the body's outer surface
        # is blended by partial volume once (its -500 HU crossing stays on the labels' edge).
        cv.paint(sl, torso, L.SKIN, _HU["skin"])
        cv.paint(sl, torso + _SKIN_MM, L.BODY_TRUNC, _HU["soft"])
        lat = 1.0 + p.fat_lateral * ((s.xr - s.xs_r).clamp(-120, 120) / 80.0) ** 2
        fat_x = fat * lat + ctx.buttock(s.z)  # (the fat over the midline fills the muscles' cleft)
        under_fat = torso + _SKIN_MM + fat_x  # < 0 below the fat
        under_fat = _paint_paraspinal(ctx, s, under_fat)
        fat_sdf = torch.maximum(-under_fat, torso + _SKIN_MM)
        cv.paint(sl, fat_sdf, L.SUBCUTANEOUS_FAT, _HU["fat"])


def _trunk_slab(ctx: _Context, sl: tuple[slice, slice, slice]) -> _Slab:
    """The coordinate frames of one z-chunk. The trunk (skin, fat) is rolled by trunk_roll
    about the vertebral bodies' line, as the spine is; the muscles follow the spine's
    rotation."""
    x, y, z = ctx.cv.coords(sl)
    roll_c, roll_s = math.cos(ctx.p.trunk_roll), math.sin(ctx.p.trunk_roll)
    spine_c, spine_s = math.cos(ctx.psi), math.sin(ctx.psi)
    xs = _interp(ctx.back_line[:, 2], ctx.back_line[:, 0], z)
    yt = _interp(ctx.back_line[:, 2], ctx.back_line[:, 1], z)
    xb_t, yb_t = (_interp(ctx.bodies[:, 2], ctx.bodies[:, k], z) for k in (0, 1))
    return _Slab(
        sl=sl,
        x=x,
        y=y,
        z=z,
        yp=_interp(ctx.skin_z, ctx.skin_y, z),
        xs=xs,
        yt=yt,
        xr=xb_t + (x - xb_t) * roll_c + (y - yb_t) * roll_s,
        yr=yb_t - (x - xb_t) * roll_s + (y - yb_t) * roll_c,
        xs_r=xb_t + (xs - xb_t) * roll_c + (yt - yb_t) * roll_s,
        xm=xs + (x - xs) * spine_c + (y - yt) * spine_s,
        ym=yt - (x - xs) * spine_s + (y - yt) * spine_c,
    )


def _torso_sdf(ctx: _Context, s: _Slab) -> torch.Tensor:
    """The body's outer surface: a rounded box tapering upward, with the furrow between the
    paraspinal bulges that the skin shows."""
    p = ctx.p
    half_w = p.torso_half_width * 1e3
    depth = p.torso_depth * 1e3
    bulge, furrow = p.muscle_bulge * 1e3, p.midline_furrow
    yc = s.yp + depth / 2
    taper = 1.0 + 0.06 * (-s.z / 125.0).clamp(-1, 1)
    torso = superellipse2(
        s.xr / (half_w * taper), (s.yr - yc) / (depth / 2), 1.0, 1.0, 2.3
    ) * torch.minimum(half_w * taper, torch.full_like(taper, depth / 2))
    back = ((yc - s.yr) / (depth / 2)).clamp(0, 1)
    mid = torch.exp(-((s.xr - s.xs_r) ** 2) / (2 * _FURROW_SIGMA**2))
    return torso + furrow * bulge * mid * back


def _paint_paraspinal(ctx: _Context, s: _Slab, under_fat: torch.Tensor) -> torch.Tensor:
    """Paraspinal muscles (multifidus and erector spinae each side) in their fascial
    envelopes, and the thoracolumbar fascia over them; over the trunk's soft tissue, before the
    fat. Returns ``under_fat`` (< 0 below the fat) lowered to the muscle lobes."""
    p, cv, sl = ctx.p, ctx.cv, s.sl
    m = p.muscle_bulk
    bulge = p.muscle_bulge * 1e3
    xm, ym, xs, yt = s.xm, s.ym, s.xs, s.yt
    # Paraspinal muscles: from the midline to their lateral border, from under the fascia
    # to the front of the transverse processes.
    y_front = _interp(ctx.tp_line[:, 2], ctx.tp_line[:, 1], s.z) + 6.0
    y_top = s.yp - 5.0
    cy, ry = (y_front + y_top) / 2, (y_front - y_top) / 2
    width = 64.0 * m
    # Their backs are convex lobes, one each side, that meet the midline down at the
    # spinous tips: fat fills the cleft between them over the tips, and the fascia follows
    # the lobes (in a transverse image two arches meeting in a V on the spinous tip).
    u = (xm - xs).abs()
    lobe_depth = _LOBE_MM + ctx.cover(s.z) + 0.5 * bulge
    inner = _TIP_HALF_MM + p.muscle_cleft * 1e3 / 2  # the lobes' medial edge
    half = (width - inner) / 2
    lobe = superellipse2(u - inner - half, ym - yt - 5.0, half, lobe_depth + 5.0, 4.0)
    deep = torch.minimum(torch.minimum(lobe, yt + 2.0 - ym), width + 12.0 - u)
    under_fat = torch.maximum(under_fat, deep)
    # Each muscle sits in its own fascial compartment: an envelope on its medial, lateral
    # and deep sides (the fat-lined fascia that outlines the muscle in transverse images),
    # painted first so that the muscles meet at the midline without it.
    muscles = []
    for side, lab in ((1.0, 87), (-1.0, 86)):
        d = _round_rect(xm - xs - side * width / 2, ym - cy, width / 2, ry, 15.0)
        d = torch.maximum(torch.maximum(d, -side * (xm - xs)), under_fat + _FASCIA_MM)
        cv.paint(sl, d - _ENVELOPE_MM, L.THORACOLUMBAR_FASCIA, _ENVELOPE_HU)
        muscles.append((d, lab))
    # The fascial septum between multifidus (medial, in the laminar groove) and the erector
    # spinae: from under the fascia, converging medially to the facets at the deep end.
    depth_frac = ((ym - y_top) / (y_front - y_top)).clamp(0, 1)
    reach = width * p.multifidus_width * (1.0 - 0.35 * depth_frac**2)
    for (d, lab), side in zip(muscles, (1.0, -1.0), strict=True):
        cv.paint(sl, d, lab, p.muscle_hu)
        septum = ((xm - xs) * side - reach).abs() - _ENVELOPE_MM / 2
        cv.paint(sl, torch.maximum(septum, d), L.THORACOLUMBAR_FASCIA, _ENVELOPE_HU)
    fascia = torch.maximum(under_fat, -(under_fat + _FASCIA_MM))
    fascia = torch.maximum(fascia, (xm - xs).abs() - (width + 8.0))
    cv.paint(sl, fascia, L.THORACOLUMBAR_FASCIA, _HU["ligament"])
    return under_fat


def _paint_spinous_ligaments(ctx: _Context) -> None:
    """Supra- and interspinous ligaments: the midline sheet from the fascia down to the
    laminae. After the trunk: it stays under the subcutaneous fat."""
    cv, tips, apex, back_line = ctx.cv, ctx.tips, ctx.apex, ctx.back_line
    top = back_line[:, 1].min() - 40.0
    sl = cv.box(np.array([-30.0 + back_line[:, 0].min(), top, tips[:, 2].min() - 30.0]),
                np.array([30.0 + back_line[:, 0].max(), apex[:, 1].max() + 5.0,
                          tips[:, 2].max() + 30.0]))  # fmt: skip
    x, y, z = cv.coords(sl)
    xt = _interp(tips[:, 2], tips[:, 0], z)
    yt = _interp(tips[:, 2], tips[:, 1], z)
    ya = _interp(apex[:, 2], apex[:, 1], z)
    half = torch.where(y < yt + 2.0, 4.0, 2.5)  # supraspinous wider than interspinous
    xc = xt - (y - yt) * math.tan(ctx.psi)  # the spinous processes' plane, rotated with the spine
    sheet = torch.maximum((x - xc).abs() - half, torch.maximum(yt - ctx.cover(z) - y, y - ya))
    keep = cv.labels[sl] != L.SUBCUTANEOUS_FAT  # under the fat only
    cv.paint(sl, torch.where(keep, sheet, sheet.clamp_min(0.5 * cv.h + 1e-3)),
             L.SPINAL_LIGAMENTS, _HU["ligament"])  # fmt: skip


def _blob(cv: _Canvas, label: int, hu: float, centre, radii, clip_body: bool = True) -> None:
    """An ellipsoid, by default only where the canvas holds generic soft tissue."""
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


def _tube(cv: _Canvas, label: int, hu: float, a, b, r: float) -> None:
    """A capsule from ``a`` to ``b`` (mm) of radius ``r``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    sl = cv.box(np.minimum(a, b) - r, np.maximum(a, b) + r)
    if sl is None:
        return
    x, y, z = cv.coords(sl)
    cv.paint(sl, capsule(x, y, z, tuple(a), tuple(b), r), label, hu)


def _paint_organs(ctx: _Context) -> None:
    """Liver and kidneys, only inside generic soft tissue (never over muscle, fat or skin):
    after the trunk and the spinous ligaments."""
    cv, yb, t12, l2 = ctx.cv, ctx.body_y, ctx.by["T12"], ctx.by["L2"]
    _blob(cv, 5, _HU["liver"], (65.0, yb(t12.centre[2]) + 80, t12.centre[2] + 55),
          (115.0, 95.0, 105.0))  # fmt: skip
    zk = l2.centre[2]
    bw2 = l2.dims.body_half_width
    _blob(cv, 3, _HU["kidney"], (-(bw2 + 52), yb(zk) + 12, zk + 5), (26.0, 22.0, 52.0))
    _blob(cv, 2, _HU["kidney"], (bw2 + 52, yb(zk) + 12, zk - 12), (26.0, 22.0, 52.0))


def _paint_iliopsoas(ctx: _Context) -> None:
    """Psoas muscles beside the bodies, growing caudally, only inside generic soft tissue:
    after the organs."""
    cv, bodies, m = ctx.cv, ctx.bodies, ctx.p.muscle_bulk
    l1, l4, l5, t12 = ctx.by["L1"], ctx.by["L4"], ctx.by["L5"], ctx.by["T12"]
    z_top = t12.centre[2]
    sl = cv.box(np.array([-120.0, cv.lo[1], ctx.z_lo]), np.array([120.0, ctx.hi[1], z_top]))
    x, y, z = cv.coords(sl)
    zc = z.clamp(l5.centre[2], l1.centre[2])
    grow = ((l1.centre[2] - zc) / (l1.centre[2] - l5.centre[2])).clamp(0, 1)
    below = (l5.centre[2] - z).clamp_min(0)
    yb_t = _interp(bodies[:, 2], bodies[:, 1], z)
    xs_t = _interp(bodies[:, 2], bodies[:, 0], z)
    rx, ry = (8.0 + 14.0 * grow) * m, (9.0 + 11.0 * grow) * m
    for side, lab in ((1.0, 89), (-1.0, 88)):
        cx = xs_t + side * (l4.dims.body_half_width + rx * 0.8 + 0.4 * below)
        d = ellipse2((x - cx) / rx, (y - yb_t - 4.0 - 0.3 * below) / ry, 1.0, 1.0) * torch.minimum(
            rx, ry
        )
        d = torch.maximum(d, z - z_top)
        d = torch.where(cv.labels[sl] == L.BODY_TRUNC, d, d.clamp_min(0.5 * cv.h + 1e-3))
        cv.paint(sl, d, lab, _HU["muscle"])


def _paint_great_vessels(ctx: _Context) -> None:
    """Aorta and inferior vena cava in front of the bodies, and the iliac vessels from their
    bifurcations; over whatever lies there (before the discs and bones)."""
    cv, xb, yb, z_lo, z_hi = ctx.cv, ctx.body_x, ctx.body_y, ctx.z_lo, ctx.z_hi
    l4, l5 = ctx.by["L4"], ctx.by["L5"]
    bd = l4.dims.body_half_depth
    z_bif = l4.centre[2] - 8.0

    def ya(zv):
        return yb(zv) + bd + 13.0

    _tube(cv, 52, _HU["blood"], (xb(z_bif) - 14, ya(z_bif), z_bif),
          (xb(z_hi) - 14, ya(z_hi), z_hi + 10), 10.0)  # fmt: skip
    z_ivc = l5.centre[2] + 5.0
    _tube(cv, 63, _HU["blood"], (xb(z_ivc) + 20, ya(z_ivc) + 1, z_ivc),
          (xb(z_hi) + 20, ya(z_hi) + 1, z_hi + 10), 11.0)  # fmt: skip
    ybot = yb(z_lo) + bd + 25.0
    _tube(cv, 65, _HU["blood"], (xb(z_bif) - 14, ya(z_bif), z_bif), (-50.0, ybot, z_lo - 10), 6.5)
    _tube(cv, 66, _HU["blood"], (xb(z_bif) - 14, ya(z_bif), z_bif), (45.0, ybot, z_lo - 10), 6.5)
    _tube(cv, 67, _HU["blood"], (xb(z_ivc) + 20, ya(z_ivc) + 1, z_ivc),
          (-40.0, ybot + 10, z_lo - 10), 7.5)  # fmt: skip
    _tube(cv, 68, _HU["blood"], (xb(z_ivc) + 20, ya(z_ivc) + 1, z_ivc),
          (55.0, ybot + 10, z_lo - 10), 7.5)  # fmt: skip


def _disc_part(up: S.Vertebra, low: S.Vertebra) -> S.Part:
    """The disc between two consecutive bodies: their kidney-shaped section, between their
    endplates, in the frame halfway between theirs."""
    e_up = up.centre - up.dims.body_half_height * up.rot[:, 2]
    e_lo = low.centre + low.dims.body_half_height * low.rot[:, 2]
    c = (e_up + e_lo) / 2
    rot = up.rot + low.rot
    s_ax = rot[:, 2] / np.linalg.norm(rot[:, 2])
    a_ax = rot[:, 1] - (rot[:, 1] @ s_ax) * s_ax
    a_ax /= np.linalg.norm(a_ax)
    frame = np.stack([np.cross(a_ax, s_ax), a_ax, s_ax], 1)
    hh = np.linalg.norm(e_up - e_lo) / 2 + 1.0
    rw = min(up.dims.body_half_width, low.dims.body_half_width) * 0.97
    rd = min(up.dims.body_half_depth, low.dims.body_half_depth) * 0.97

    def disc(u, v, w, rw=rw, rd=rd, hh=hh):
        sec = S.body_section(u, v, rw, rd)
        qs = w.abs() - hh
        out = torch.sqrt(sec.clamp_min(0) ** 2 + qs.clamp_min(0) ** 2)
        return out + torch.maximum(sec, qs).clamp_max(0)

    return S.Part(c, frame, (-rw, -rd, -hh), (rw, rd, hh), disc)


def _paint_discs(ctx: _Context) -> None:
    """Intervertebral discs, T12/L1 to L5/S1; before the canals and bones, which overlap
    them."""
    for up, low in zip(ctx.verts[:-1], ctx.verts[1:], strict=True):
        got = ctx.cv.union([_disc_part(up, low)])
        if got is not None:
            ctx.cv.paint(got[0], got[1], L.INTERVERTEBRAL_DISCS, _HU["disc"])


def _paint_canals(ctx: _Context) -> None:
    """Spinal canals (CSF) of every level, then the cord down to its conus at L1; after the
    discs, before the flavum and the bones (each bone is carved around its own canal). All
    canals come before the cord because neighbouring canals overlap at the discs."""
    cv = ctx.cv
    canals = []
    for v in ctx.verts:
        bh = v.dims.body_half_height
        reach = v.dims.canal_half_width + 2.0
        part = S.Part(v.centre, v.rot, (-reach, v.canal_back - 2.0, -bh - 12.0),
                      (reach, v.canal_a + v.dims.canal_half_depth + 2.0, bh + 12.0),
                      lambda u, a, s, v=v: S.canal_sdf(v, u, a, s))  # fmt: skip
        sl = cv.box(*part.world_box(2 * cv.h))
        if sl is None:
            continue
        lq, aq, sq = S.local_coords(v.centre, v.rot, *cv.coords(sl))
        canal = S.canal_sdf(v, lq, aq, sq)
        cv.paint(sl, canal, L.SPINAL_CANAL, _HU["csf"])
        canals.append((v, sl, lq, aq, sq))
    for v, sl, lq, aq, sq in canals:
        bh = v.dims.body_half_height
        if v.level in ("T12", "L1"):  # the cord ends (conus) at the L1 body
            s0 = -0.2 * bh if v.level == "L1" else -bh - 12.0
            cord = ellipse2(lq, aq - v.canal_a, 4.5, 4.0)
            qs = (sq - (s0 + bh + 12) / 2).abs() - (bh + 12 - s0) / 2
            cord = torch.maximum(cord, qs)
            cv.paint(sl, cord, 79, _HU["cord"])


def _paint_flavum(ctx: _Context) -> None:
    """Ligamentum flavum, the canals' back wall between the laminae; after the canals, before
    the bones."""
    for up, down in zip(ctx.verts[:-1], ctx.verts[1:], strict=True):
        got = ctx.cv.union([S.flavum(up, down)])
        if got is not None:
            ctx.cv.paint(got[0], got[1], L.SPINAL_LIGAMENTS, _HU["ligament"])


def _paint_vertebrae(ctx: _Context) -> None:
    """T12-S1, each carved around its own canal (cortex over cancellous bone); after the soft
    tissue, so bone wins where they meet."""
    verts = ctx.verts
    for i, v in enumerate(verts):
        above = verts[i - 1] if i > 0 else None
        below = verts[i + 1] if i + 1 < len(verts) else None
        got = ctx.cv.union(S.vertebra_parts(v, above, below))
        if got is None:
            continue
        sl, bone, body = got
        lq, aq, sq = S.local_coords(v.centre, v.rot, *ctx.cv.coords(sl))
        bone = torch.maximum(bone, -S.canal_sdf(v, lq, aq, sq))
        ctx.cv.paint_bone(sl, bone, body, v.label, ctx.p)


def _paint_pelvis(ctx: _Context) -> None:
    """Iliac bones (hip_left 77, hip_right 78), then the sacrum below S1 over them; after the
    vertebrae."""
    cv, p = ctx.cv, ctx.p
    l4, l5 = ctx.by["L4"], ctx.by["L5"]
    for side, lab in ((-1.0, 77), (1.0, 78)):
        got = cv.union(S.ilium_parts(l5, l4, side, p.crest_level))
        if got is not None:
            cv.paint_bone(got[0], got[1], torch.full_like(got[1], 1e3), lab, p)
    for k, seg in enumerate(ctx.sacrum):
        got = cv.union(S.sacral_parts(seg, k, p.vertebra_scale))
        if got is None:
            continue
        sl, bone, body = got
        lq, aq, sq = S.local_coords(seg.centre, seg.rot, *cv.coords(sl))
        bone = torch.maximum(bone, -S.canal_sdf(seg, lq, aq, sq, extra=1.0))
        cv.paint_bone(sl, bone, body, L.LABEL_IDS["sacrum"], p)


def _paint_ribs(ctx: _Context) -> None:
    """Lower ribs (11 and 12) from T12 and the level above; the last bones painted."""
    t12 = ctx.by["T12"]
    for side, r11, r12 in ((-1.0, 102, 103), (1.0, 114, 115)):
        a_c = t12.canal_a
        cw = t12.dims.canal_half_width
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
            got = ctx.cv.union([S._capsule_part(seg[0], seg[1], r)])
            if got is not None:
                ctx.cv.paint_bone(got[0], got[1], torch.full_like(got[1], 1e3), lab, ctx.p)


def _noisy_ct(ctx: _Context, seed: int) -> torch.Tensor:
    """The painted CT with Gaussian CT noise, in integer HU (so the int16 NIfTI round trip is
    exact); last, after the bone cover."""
    gen = torch.Generator().manual_seed(int(seed))
    noise = torch.randn(ctx.cv.shape, generator=gen, dtype=torch.float32)
    return (ctx.cv.ct + ctx.p.ct_noise_hu * noise).round_().clamp_(-1024, 3071)


def _affine(ctx: _Context) -> np.ndarray:
    """Voxel to world (m) of the canvas."""
    affine = np.diag([ctx.p.spacing, ctx.p.spacing, ctx.p.spacing, 1.0])
    affine[:3, 3] = ctx.cv.lo * 1e-3
    return affine


def _meta(ctx: _Context, seed: int) -> dict:
    """Provenance: seed, generator version, the resolved parameters and each vertebra's body
    centroid and frame."""
    return {
        "source": "sonogym.make_phantom",
        "seed": int(seed),
        "generator_version": GENERATOR_VERSION,
        "params": dataclasses.asdict(ctx.p),
        "vertebrae": {
            v.level: {"centre_m": (S.body_centroid(v) * 1e-3).tolist(), "rotation": v.rot.tolist()}
            for v in ctx.verts
        },
    }


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
