"""Real-derived patients: anatomically varied copies of a TotalSegmentator subject, by seed.

``make_variant(folder, index)`` warps a real subject (CT and labels together, one displacement
field: CT trilinear, labels nearest) into variant ``index``, cropped to the lumbar spine and the
back; its landmarks are planned on the warped masks (``Patient.landmarks``). ``load_variant``
caches it on disk like ``load_phantom`` (``sonogym.anatomy.cache``), so a cohort of real-derived
patients is as cheap to reuse as phantoms. The same subject, index, spacing and parameters give
the same volumes bit for bit.

The deformation, applied as a backward map from each output voxel to the source (all in the
source's patient frame, measured on its landmarks), composes, in this order from the output:

* a smooth random displacement: cubic spline through a lattice of ``LATTICE`` (50 mm) with
  Gaussian control displacements of ``JITTER`` (1.5 mm) per axis;
* soft tissue: the depth from the back's skin to the spinous processes' tips (skin, fat, the
  muscle behind the tips) scaled by ``soft_tissue_scale``;
* lordosis: the lumbar spine bent in the sagittal plane about L3's body (constant added
  curvature), so the angle between L1's and L5's superior axes grows by ``lordosis_change``;
* per level: the segment (body and the disc below) stretched along the spine by
  ``segment_scale`` and the vertebra's axial size by ``size_scale`` (fading to 1 from 50 to
  100 mm from the spine's axis, so the skin keeps its shape).

Ranges (``VARIANT_RANGES``) keep each parameter within about one standard deviation of adult
morphometry around the source subject: lumbar lordosis 40-60 deg (SD about 10 deg, Been & Kalichman
2014); lumbar body height and width SD 5-8 % of the mean (Zhou et al. 2000, Panjabi 1992);
posterior soft tissue over the laminae 35-65 mm (docs/anatomy.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from sonogym.anatomy import labels as L
from sonogym.anatomy.cache import cached_patient
from sonogym.anatomy.patient import Patient, PatientError
from sonogym.anatomy.phantom import cache_dir
from sonogym.anatomy.totalseg import SPACING_RANGE, load_totalsegmentator

#: Bump when the generator's output changes, so stale cache entries are not reused.
VARIANT_VERSION = 1
#: Control-point spacing (m) and per-axis standard deviation (m) of the random displacement.
LATTICE = 0.05
JITTER = 0.0015
#: Most memory (bytes) a variant's full CT and labels may take while it is built and cropped
#: (an env keeps only its slicer's crop, ~30 MB at 1 mm); the crop narrows to keep to it.
MAX_VARIANT_BYTES = 64_000_000
#: Crop around the lumbar spine (m): half-width (navigation's +-90 mm workspace plus the image's
#: half-width, so no probe image reaches past the volume), behind the skin, in front of the
#: bodies, and above L1 / below L5.
_CROP_HALF_WIDTH = 0.13
_CROP_BEHIND_SKIN = 0.025
_CROP_FRONT = 0.045
_CROP_ENDS = 0.03
_SIZE_FADE = (0.05, 0.10)  # m from the spine's axis: full size change inside, none outside
_LEVELS = tuple(L.LUMBAR_VERTEBRAE)

#: Drawn parameters: name -> (low, high); per-level ones are drawn once for each of L1-L5.
VARIANT_RANGES: dict[str, tuple[float, float]] = {
    "lordosis_change": (-0.15, 0.15),  # rad (about +-9 deg)
    "soft_tissue_scale": (0.75, 1.35),  # skin to spinous tips
    "segment_scale": (0.93, 1.07),  # per level, along the spine
    "size_scale": (0.93, 1.07),  # per level, axial
}


@dataclass(frozen=True)
class VariantParams:
    """One variant's deformation (``None`` fields are drawn from the seed; per-level tuples hold
    L1..L5)."""

    spacing: float = 0.001  # m, isotropic voxel size of the variant
    lordosis_change: float | None = None  # rad, added to the L1-L5 angle
    soft_tissue_scale: float | None = None  # unitless, skin-to-spinous-tip depth
    segment_scale: tuple[float, ...] | None = None  # unitless per level, body + disc height
    size_scale: tuple[float, ...] | None = None  # unitless per level, axial size
    jitter: float = JITTER  # m, random displacement per axis (standard deviation)

    def __post_init__(self) -> None:
        lo, hi = SPACING_RANGE
        if not lo <= self.spacing <= hi:
            raise ValueError(
                f"variant spacing {self.spacing} m is outside {lo * 1e3:g}-{hi * 1e3:g} mm"
            )
        for k in ("segment_scale", "size_scale"):
            v = getattr(self, k)
            if v is not None and (len(v) != len(_LEVELS) or min(v) <= 0):
                raise ValueError(f"{k} must hold 5 positive scales (L1..L5), got {v!r}")

    def resolved(self, seed: int) -> VariantParams:
        """A copy with every ``None`` field drawn from ``seed`` (each always drawn, so fixing one
        leaves the others' draws unchanged)."""
        rng = np.random.default_rng([VARIANT_VERSION, seed])
        draws = {}
        for k, (lo, hi) in VARIANT_RANGES.items():
            per_level = k in ("segment_scale", "size_scale")
            v = rng.uniform(lo, hi, len(_LEVELS) if per_level else None)
            draws[k] = tuple(float(x) for x in v) if per_level else float(v)
        return dataclasses.replace(
            self, **{k: v for k, v in draws.items() if getattr(self, k) is None}
        )


def parse_variant(spec: str) -> tuple[str, int] | None:
    """``"DIR@7"`` -> (``"DIR"``, 7) when DIR is a folder and ``DIR@7`` itself is not a path;
    else None (the spec is a plain folder)."""
    folder, at, index = spec.rpartition("@")
    if not at or not index.isdigit() or Path(spec).exists() or not Path(folder).is_dir():
        return None
    return folder, int(index)


def make_variant(folder: str | Path, index: int, params: VariantParams | None = None) -> Patient:
    """Variant ``index`` of the subject in ``folder`` (module docstring), without caching."""
    p = (params or VariantParams()).resolved(index)
    source = _source(str(Path(folder).resolve()), p.spacing)
    ct, labels, affine = _warp(source, p, np.random.default_rng([VARIANT_VERSION, index, 1]))
    meta = {
        "source": str(folder),
        "variant": int(index),
        "params": dataclasses.asdict(p),
        "speckle_seed": _variant_seed(source.meta.get("speckle_seed", 0), index),
    }
    meta = json.loads(json.dumps(meta))  # as the cache's sidecar holds it (tuples as lists)
    return Patient(
        ct=torch.from_numpy(ct),
        labels=torch.from_numpy(labels),
        affine=affine,
        name=f"{Path(folder).name}@{index}",
        meta=meta,
    )


def load_variant(
    folder: str | Path, index: int, params: VariantParams | None = None, cache: bool | Path = True
) -> Patient:
    """``make_variant`` with the on-disk cache of ``load_phantom`` (``$SONOGYM_CACHE``), keyed by
    the subject's files (paths, sizes, modification times), the index, the resolved parameters
    and ``VARIANT_VERSION``."""
    if cache is False:
        return make_variant(folder, index, params)
    stem = (cache_dir() if cache is True else Path(cache)) / (
        f"variant-{Path(folder).name}-{index}-{variant_cache_key(folder, index, params)}"
    )
    return cached_patient(stem, lambda: make_variant(folder, index, params), "variant")


def variant_cache_key(folder: str | Path, index: int, params: VariantParams | None = None) -> str:
    """Stable key of a variant: generator version, the subject's files, index, parameters."""
    folder = Path(folder).resolve()
    if not folder.is_dir():
        raise FileNotFoundError(f"patient folder {folder} does not exist or is not a folder")
    files = sorted(f for f in folder.rglob("*") if f.is_file())
    stats = [(str(f.relative_to(folder)), f.stat().st_size, f.stat().st_mtime_ns) for f in files]
    p = (params or VariantParams()).resolved(index)
    blob = json.dumps(
        {"v": VARIANT_VERSION, "folder": str(folder), "files": stats, "index": int(index),
         "params": dataclasses.asdict(p)},
        sort_keys=True,
    )  # fmt: skip
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------- internals


@lru_cache(maxsize=1)
def _source(folder: str, spacing: float) -> Patient:
    """The subject at ``spacing`` with its L1-L5 frames (variants of one subject in a row load
    it once)."""
    patient = load_totalsegmentator(folder, spacing=spacing, target="L4")
    missing = [lv for lv in _LEVELS if lv not in patient.landmarks.vertebrae]
    if missing:
        raise PatientError(
            f"{folder}: variants need frames of L1-L5; {missing} have none "
            f"({ {lv: patient.landmarks.refused.get(lv, 'absent') for lv in missing} })"
        )
    return patient


def _variant_seed(source_seed: int, index: int) -> int:
    h = hashlib.blake2b(f"{source_seed}@{index}".encode(), digest_size=8)
    return int.from_bytes(h.digest(), "little") & 0x7FFFFFFF


class _Spine:
    """The source's lumbar geometry the maps are built on (patient frame, m): body centres of
    L1-L5 (head to foot), the spinous tips' y per level, the skin's y over the spine."""

    def __init__(self, source: Patient) -> None:
        lm = source.landmarks
        self.centres = np.array([lm.vertebrae[lv].centre for lv in _LEVELS])
        lab = source.labels.numpy()
        tips = []
        for lv in _LEVELS:
            idx = np.argwhere(lab == L.VERTEBRA_IDS[lv])
            tips.append(source.origin[1] + idx[:, 1].min() * source.spacing[1])
        self.tip_y = np.array(tips)
        self.z = self.centres[:, 2]
        order = np.argsort(self.z)  # increasing z for np.interp
        self.z_sorted, self.order = self.z[order], order

    def at(self, values: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Per-level ``values`` (L1..L5) interpolated at heights ``z`` (held past the ends)."""
        return np.interp(z, self.z_sorted, np.asarray(values)[self.order])


def variant_grid(source: Patient, spacing: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Origin (3,) in {P} and shape of the grid variants of ``source`` get at ``spacing``: the
    lumbar spine (+-30 mm past L1 and L5), +-130 mm to the sides (narrower where the CT and labels
    would exceed ``MAX_VARIANT_BYTES``), from behind the skin (room for the thickest soft tissue)
    to 45 mm in front of the bodies."""
    return _crop_box(source, _Spine(source), spacing)


def _crop_box(source: Patient, spine: _Spine, spacing: float) -> tuple[np.ndarray, tuple]:
    lab = source.labels.numpy()
    lum = np.argwhere(np.isin(lab, list(L.LUMBAR_VERTEBRAE.values())))
    z_lo = source.origin[2] + lum[:, 2].min() * source.spacing[2] - _CROP_ENDS
    z_hi = source.origin[2] + lum[:, 2].max() * source.spacing[2] + _CROP_ENDS
    x_c = spine.centres[:, 0].mean()
    col = lab[:, :, int(round((spine.z.mean() - source.origin[2]) / source.spacing[2]))]
    i_c = int(round((x_c - source.origin[0]) / source.spacing[0]))
    skin_j = np.flatnonzero(col[i_c] > 0)
    skin_y = source.origin[1] + (skin_j.min() if len(skin_j) else 0) * source.spacing[1]
    scale_max = VARIANT_RANGES["soft_tissue_scale"][1]
    behind = (spine.tip_y.min() - skin_y) * (scale_max - 1) + _CROP_BEHIND_SKIN
    y_lo, y_hi = skin_y - behind, spine.centres[:, 1].max() + _CROP_FRONT
    half = _CROP_HALF_WIDTH
    depth_n = int(np.ceil((y_hi - y_lo) / spacing)) + 1
    height_n = int(np.ceil((z_hi - z_lo) / spacing)) + 1
    max_voxels = MAX_VARIANT_BYTES // 5  # float32 CT + uint8 labels
    half = min(half, (max_voxels / (depth_n * height_n) - 1) * spacing / 2)
    width_n = int(np.floor(2 * half / spacing)) + 1
    return np.array([x_c - half, y_lo, z_lo]), (width_n, depth_n, height_n)


def _smooth_field(rng, origin, shape, spacing, jitter) -> tuple[np.ndarray, float]:
    """Random displacement (3, X', Y', Z') on every 8th voxel of the grid, and that stride (m)."""
    extent = np.array(shape) * spacing
    lattice = rng.normal(0.0, jitter, (3, *(np.ceil(extent / LATTICE).astype(int) + 3)))
    stride = 8 * spacing
    coarse = [np.arange(0, e + stride, stride) / LATTICE + 1.0 for e in extent]
    grid = np.meshgrid(*coarse, indexing="ij")
    return np.stack([ndimage.map_coordinates(c, grid, order=3) for c in lattice]), stride


def _warp(source: Patient, p: VariantParams, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(CT float32 in integer HU, labels uint8, affine) of the variant on its cropped grid."""
    spine = _Spine(source)
    h = p.spacing
    origin, shape = _crop_box(source, spine, h)
    field, stride = _smooth_field(rng, origin, shape, h, p.jitter)
    c3 = spine.centres[2]
    span = spine.z[0] - spine.z[-1]  # L1 above L5
    # Added curvature (rad per m): lordosis grows when the spine's ends turn back about L3, the
    # most anterior body (prone frame: +y anterior).
    kappa = -p.lordosis_change / span
    # Along the spine: each level's interval to the next stretched by their mean segment scale,
    # L3 fixed; z_out -> z_src is piecewise linear, slope 1 beyond L1 and L5.
    seg = np.asarray(p.segment_scale)
    gaps = np.diff(spine.z)  # negative: head to foot
    new_z = np.concatenate([[0.0], np.cumsum(gaps * (seg[:-1] + seg[1:]) / 2)])
    new_z += spine.z[2] - new_z[2]
    knots_out = np.concatenate([[new_z[0] + 1.0], new_z, [new_z[-1] - 1.0]])[::-1]
    knots_src = np.concatenate([[spine.z[0] + 1.0], spine.z, [spine.z[-1] - 1.0]])[::-1]
    size = np.asarray(p.size_scale)
    src_ct, src_lab = source.ct.numpy(), source.labels.numpy()
    ct = np.empty(shape, np.float32)
    labels = np.empty(shape, np.uint8)
    xs = origin[0] + h * np.arange(shape[0])
    ys = origin[1] + h * np.arange(shape[1])
    for k0 in range(0, shape[2], 16):  # slabs of z keep the coordinate arrays small
        zs = origin[2] + h * np.arange(k0, min(k0 + 16, shape[2]))
        x, y, z = np.meshgrid(xs, ys, zs, indexing="ij")
        # 1. random smooth displacement (trilinear from the every-8th-voxel field)
        fi = [(v - o) / stride for v, o in zip((x, y, z), origin, strict=True)]
        x = x + ndimage.map_coordinates(field[0], fi, order=1, mode="nearest")
        y = y + ndimage.map_coordinates(field[1], fi, order=1, mode="nearest")
        z = z + ndimage.map_coordinates(field[2], fi, order=1, mode="nearest")
        # 2. soft tissue behind the spinous tips
        tip = spine.at(spine.tip_y, z)
        y = np.where(y < tip, tip + (y - tip) / p.soft_tissue_scale, y)
        # 3. lordosis: the bend moved the spine's axis at height zeta from L3 by kappa zeta^2 / 2
        # and turned its axial slab by kappa zeta about it; undone here
        zeta = z - c3[2]
        phi = kappa * zeta
        y_spine = spine.at(spine.centres[:, 1], z)
        dy = y - y_spine - 0.5 * kappa * zeta**2
        y, z = y_spine + np.cos(phi) * dy, z + np.sin(phi) * dy
        # 4. per-level segment height (z) and axial size (x, y about the spine's axis)
        z = np.interp(z, knots_out, knots_src)
        ax, ay = spine.at(spine.centres[:, 0], z), spine.at(spine.centres[:, 1], z)
        r = np.hypot(x - ax, y - ay)
        fade = np.clip((_SIZE_FADE[1] - r) / (_SIZE_FADE[1] - _SIZE_FADE[0]), 0.0, 1.0)
        s = 1.0 + (spine.at(size, z) - 1.0) * fade
        x, y = ax + (x - ax) / s, ay + (y - ay) / s
        idx = [
            (v - o) / sp for v, o, sp in zip((x, y, z), source.origin, source.spacing, strict=True)
        ]
        sl = np.s_[:, :, k0 : k0 + len(zs)]
        ct[sl] = ndimage.map_coordinates(src_ct, idx, order=1, mode="constant", cval=-1024.0)
        labels[sl] = ndimage.map_coordinates(src_lab, idx, order=0, mode="constant", cval=0)
    affine = np.diag([h, h, h, 1.0])
    affine[:3, 3] = origin
    return np.rint(ct), labels, affine
