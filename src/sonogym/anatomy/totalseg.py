"""Read and write patients in the TotalSegmentator folder layout.

A subject folder holds ``ct.nii.gz`` (or ``ct.nii``) and either ``segmentations/<class>.nii.gz``
(one binary mask per TotalSegmentator v2 class name; project names such as ``body_trunc``,
``subcutaneous_fat``, ``intervertebral_discs``, ``skin`` and ``spinal_canal`` are read too) or
one combined label map ``combined_label_map.nii.gz`` with the ids of ``sonogym.anatomy.labels``.

Loading reorients to canonical RAS, converts millimetres to metres, resamples onto an
axis-aligned isotropic grid (CT trilinear, labels nearest) and then derives missing body, skin and
fat labels from the CT on that grid (so a coarse CT loaded at 1 mm gets a 2 mm skin).

Every file is a user's: the loader refuses, with a :class:`PatientError` naming the file and the
fix, what it cannot interpret correctly (see ``docs/anatomy.md``, "Refusals"): headers whose
voxel data would not fit in memory or cannot be in the file, implausible voxel sizes or units,
truncated files, non-finite or non-HU CT values, non-binary masks (unless ``mask_threshold`` is
given), a target vertebra cut by the field of view or of implausible size.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import math
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from nibabel import orientations as ornt_
from scipy import ndimage

from sonogym.anatomy import labels as L
from sonogym.anatomy.patient import Patient, PatientError
from sonogym.memory import available_memory
from sonogym.runs import atomic_write_bytes, atomic_write_text

COMBINED_NAMES = ("combined_label_map", "labels")
_FAT_HU = (-190.0, -30.0)  # HU window of adipose tissue
_FAT_MAX_DEPTH = 0.04  # m: fat within this depth of the body surface counts as subcutaneous
_FAT_DEPTH_GRID = 0.003  # m: coarsest grid the fat depth is measured on (40 mm cut-off)
_SKIN_THICKNESS = 0.002  # m
_BODY_HU = -500.0

#: Voxel edge (m) a file may have; outside it the header's size or units are wrong.
VOXEL_SIZE_RANGE = (0.0001, 0.006)
#: ``spacing`` (m) the loader resamples to.
SPACING_RANGE = (0.00025, 0.005)
#: Upper bound on the memory one load may use (bytes); the loader also keeps to 80 % of the
#: memory available when it starts.
MAX_LOAD_BYTES = 32 * 2**30
#: Working memory per voxel of the resampled grid (CT, labels, resampling and tissue masks).
_BYTES_PER_VOXEL = 24
#: deflate cannot compress by more than 1032:1, so a .nii.gz claiming more voxel bytes than this
#: times its size is truncated or forged.
_DEFLATE_MAX_RATIO = 1032
#: Median HU of segmented bone in a CT in Hounsfield units (cancellous 150-250, cortex > 1000;
#: partial volume lowers it on coarse grids).
_BONE_MEDIAN_HU = (50.0, 1000.0)
#: A CT in HU has air (-1000) or fat (-100) somewhere: its minimum is below this.
_HU_MIN_BELOW = -50.0
#: Volume (mL) of an adult lumbar vertebra mask (body and posterior elements: ~40-70 mL).
_VERTEBRA_ML = (15.0, 200.0)
#: Voxels hashed for the speckle seed (a strided sample beyond this keeps hashing cheap).
_HASH_VOXELS = 1 << 22


def _nifti(folder: Path, stem: str) -> Path | None:
    found = [
        folder / f"{stem}{ext}" for ext in (".nii.gz", ".nii") if (folder / f"{stem}{ext}").exists()
    ]
    if len(found) > 1:
        raise PatientError(f"both {found[0]} and {found[1]} exist; keep one")
    return found[0] if found else None


def _available_memory() -> int:
    """Bytes of memory available now (``sonogym.memory``; the load cap if unknown)."""
    avail = available_memory()
    return MAX_LOAD_BYTES if avail is None else avail


def _check_memory(needed: float, what: str) -> None:
    cap = min(MAX_LOAD_BYTES, 0.8 * _available_memory())
    if needed > cap:
        raise PatientError(
            f"{what} needs about {needed / 2**30:.1f} GiB of memory, more than this load may use "
            f"({cap / 2**30:.1f} GiB: 80 % of the memory available, at most "
            f"sonogym.anatomy.totalseg.MAX_LOAD_BYTES); crop the scan to the lumbar spine or "
            "load it at a coarser spacing"
        )


class _Nifti:
    """A NIfTI file whose header has been checked; the voxel data is read by :meth:`read`."""

    def __init__(self, path: Path, what: str) -> None:
        self.path, self.what = path, what
        try:
            img = nib.load(str(path))
        except Exception as e:  # nibabel raises several types for broken files
            raise PatientError(f"cannot read {what} {path}: {e}; is it a NIfTI file?") from e
        if not isinstance(img, nib.Nifti1Image | nib.Nifti2Image):
            raise PatientError(f"{path}: {what} is not a NIfTI-1/2 image ({type(img).__name__})")
        shape = tuple(int(s) for s in img.shape)
        if len(shape) == 4 and shape[3] == 1:
            shape = shape[:3]
        if len(shape) != 3 or min(shape) < 1:
            raise PatientError(f"{path}: {what} must be a 3-D volume, got shape {img.shape}")
        dtype = img.get_data_dtype()
        if dtype.fields is not None or not (
            np.issubdtype(dtype, np.integer) or np.issubdtype(dtype, np.floating)
        ):
            raise PatientError(
                f"{path}: {what} has voxel type {dtype}; expected integers or floats"
            )
        self.img, self.shape, self.dtype = img, shape, dtype
        self._check_file_holds_data()
        self.affine = self._affine_in_metres()

    @property
    def voxels(self) -> int:
        return math.prod(self.shape)

    def _check_file_holds_data(self) -> None:
        """Refuse a header claiming more voxel data than the file can hold (before allocating)."""
        claimed = self.voxels * self.dtype.itemsize + int(self.img.header.get("vox_offset", 352))
        size = self.path.stat().st_size
        compressed = self.path.name.endswith(".gz")
        if (compressed and claimed > _DEFLATE_MAX_RATIO * size + 4096) or (
            not compressed and claimed > size
        ):
            raise PatientError(
                f"{self.path}: the header claims {self.shape} voxels of {self.dtype} "
                f"({claimed / 2**20:.1f} MiB) but the file holds {size} bytes"
                f"{' compressed' if compressed else ''}: it is truncated or its header is wrong; "
                "re-export it"
            )

    def _affine_in_metres(self) -> np.ndarray:
        aff = np.asarray(self.img.affine, dtype=np.float64)
        if not np.isfinite(aff).all() or abs(np.linalg.det(aff[:3, :3])) < 1e-12:
            raise PatientError(
                f"{self.path}: {self.what} has a singular or non-finite affine (sform/qform); "
                "fix the NIfTI header's orientation"
            )
        try:
            unit = self.img.header.get_xyzt_units()[0]
        except KeyError:
            unit = "unknown"
        scale = {"meter": 1.0, "mm": 1e-3, "micron": 1e-6}.get(unit, 1e-3)
        sizes = np.linalg.norm(aff[:3, :3], axis=0) * scale
        lo, hi = VOXEL_SIZE_RANGE
        if not ((sizes >= lo) & (sizes <= hi)).all():
            mm = np.round(sizes * 1e3, 4).tolist()
            hint = ""
            as_mm = sizes / scale * 1e-3
            if unit != "mm" and ((as_mm >= lo) & (as_mm <= hi)).all():
                hint = (
                    f"; the header's units are '{unit}' but the voxel sizes read as millimetres "
                    "would be plausible: set xyzt_units to mm (nibabel: "
                    "img.header.set_xyzt_units('mm'))"
                )
            raise PatientError(
                f"{self.path}: voxel size {mm} mm (units '{unit}') is outside the plausible "
                f"{lo * 1e3:g}-{hi * 1e3:g} mm for a CT{hint or '; check pixdim and xyzt_units'}"
            )
        aff[:3, :] *= scale
        return aff

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(voxel array in canonical RAS order, its affine in metres)."""
        try:
            arr = np.asanyarray(self.img.dataobj)
        except Exception as e:  # EOFError, zlib.error, OSError, ValueError ...
            raise PatientError(
                f"cannot read the voxel data of {self.what} {self.path}: "
                f"{type(e).__name__}: {e}; the file is truncated or corrupt, re-export it"
            ) from e
        arr = arr.reshape(self.shape)
        ornt = ornt_.io_orientation(self.affine)
        if np.array_equal(ornt, [[0, 1], [1, 1], [2, 1]]):
            return arr, self.affine
        arr = ornt_.apply_orientation(arr, ornt)
        return arr, self.affine @ ornt_.inv_ornt_aff(ornt, self.shape)

    def same_grid(self, ct: _Nifti) -> None:
        if self.shape != ct.shape:
            raise PatientError(
                f"{self.path}: label grid (shape {self.shape}) differs from the CT grid "
                f"{ct.path} (shape {ct.shape}); resample the labels onto the CT grid"
            )
        diff = np.abs(self.affine - ct.affine)
        if diff.max() > 1e-6:  # metres: 1 um
            moved = np.linalg.norm(self.affine[:3, 3] - ct.affine[:3, 3]) * 1e3
            what = (
                f"its origin is {moved:.3g} mm away from the CT's"
                if diff[:3, :3].max() <= 1e-6
                else "its voxel axes (orientation or voxel size) differ from the CT's"
            )
            raise PatientError(
                f"{self.path}: same shape {self.shape} as the CT {ct.path}, but {what} (NIfTI "
                "affine); the mask does not lie on the CT's voxels: resample it onto the CT grid "
                "or fix its header"
            )


def _check_spacing(spacing: float | None) -> float | None:
    if spacing is None:
        return None
    lo, hi = SPACING_RANGE
    if isinstance(spacing, bool) or not isinstance(spacing, int | float) or not lo <= spacing <= hi:
        raise PatientError(
            f"spacing {spacing!r} must be None (keep the file's grid) or a voxel size in metres "
            f"within {lo * 1e3:g}-{hi * 1e3:g} mm (1 mm = 0.001)"
        )
    return float(spacing)


def load_totalsegmentator(
    folder: str | Path,
    spacing: float | None = 0.001,
    target: str | None = None,
    name: str | None = None,
    mask_threshold: float | None = None,
) -> Patient:
    """Load a TotalSegmentator subject folder as a :class:`Patient`.

    Args:
        folder: subject folder with ``ct.nii[.gz]`` and ``segmentations/`` or a combined map.
        spacing: isotropic voxel size in metres to resample to (0.25-5 mm); ``None`` keeps the
            file's grid when it is already isotropic and axis-aligned (else uses its finest
            spacing).
        target: a lumbar vertebra ("L4") that must be present, whole (not touching the field of
            view's edge) and of adult size, else :class:`PatientError`.
        name: patient name (default: the folder name).
        mask_threshold: per-class masks must be binary (0 and one other value) unless this is
            given; then a voxel belongs to the class where the mask value is >= it (e.g. 0.5 for
            probability maps).

    Raises:
        FileNotFoundError: the folder, its CT or its labels are missing.
        PatientError: a file is unreadable or cannot be interpreted correctly (message: the file,
            what is wrong and the fix).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"patient folder {folder} does not exist or is not a folder")
    spacing = _check_spacing(spacing)
    if target is not None and target not in L.LUMBAR_VERTEBRAE:
        raise PatientError(
            f"target {target!r} must be a lumbar vertebra {list(L.LUMBAR_VERTEBRAE)}"
        )
    if mask_threshold is not None and not (
        isinstance(mask_threshold, int | float)
        and 0.0 < mask_threshold
        and math.isfinite(mask_threshold)
    ):
        raise PatientError(f"mask_threshold {mask_threshold!r} must be a positive number or None")
    ct_path = _nifti(folder, "ct")
    if ct_path is None:
        raise FileNotFoundError(
            f"no CT in {folder}: expected {folder / 'ct.nii.gz'} (TotalSegmentator layout)"
        )
    ct_file = _Nifti(ct_path, "CT")
    comb = next((p for s in COMBINED_NAMES if (p := _nifti(folder, s)) is not None), None)
    seg_dir = folder / "segmentations"
    if comb is None and not seg_dir.is_dir():
        raise FileNotFoundError(
            f"no labels in {folder}: expected {seg_dir}/<class>.nii.gz or "
            f"{folder / 'combined_label_map.nii.gz'}"
        )
    # Native arrays: the file's CT (as float32), the label map (uint8) and, while reading one
    # mask at a time, the mask itself.
    _check_memory(ct_file.voxels * (ct_file.dtype.itemsize + 4 + 1 + 8), f"{ct_path}")
    raw, affine = ct_file.read()
    ct = np.asarray(raw, dtype=np.float32)
    del raw
    _check_hu(ct, ct_path)
    ignored: list[str] = []
    if comb is not None:
        labels = _read_combined(_Nifti(comb, "label map"), ct_file)
    else:
        labels, ignored = _combine_masks(seg_dir, ct_file, mask_threshold, ct.shape)
    _check_bone_hu(ct, labels, ct_path)
    if target is not None:
        _check_target(labels, affine, target, folder)
    speckle = _content_seed(ct, labels, affine)
    ct, labels, affine = _to_isotropic(ct, labels, affine, spacing, folder)
    labels = _complete_soft_tissue(labels, ct, np.diag(affine)[:3])
    meta = {"source": str(folder), "speckle_seed": speckle}
    if ignored:
        meta["ignored_masks"] = ignored
    info = folder / "sonogym.json"
    if info.exists():
        meta = {**_read_info(info), **meta}
    return Patient(
        ct=torch.from_numpy(np.ascontiguousarray(ct, dtype=np.float32)),
        labels=torch.from_numpy(np.ascontiguousarray(labels, dtype=np.uint8)),
        affine=affine,
        name=name or folder.name,
        meta=meta,
    )


def _read_info(info: Path) -> dict:
    try:
        meta = json.loads(info.read_text()).get("meta", {})
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError) as e:
        raise PatientError(
            f"{info} is not a sonogym.json ({type(e).__name__}: {e}); fix or delete it "
            "(it only carries the subject's provenance)"
        ) from e
    if not isinstance(meta, dict):
        raise PatientError(f"{info}: 'meta' must be a JSON object; fix or delete the file")
    return meta


# ----------------------------------------------------------------------------- value checks


def _check_hu(ct: np.ndarray, path: Path) -> None:
    finite = np.isfinite(ct)
    if not finite.all():
        n_nan, n_inf = int(np.isnan(ct).sum()), int(np.isinf(ct).sum())
        raise PatientError(
            f"{path}: CT contains {n_nan} NaN and {n_inf} inf values; replace them (e.g. by "
            "-1024 HU, air) before loading"
        )
    lo, hi = float(ct.min()), float(ct.max())
    if lo > _HU_MIN_BELOW:
        raise PatientError(
            f"{path}: CT values span {lo:g} to {hi:g} with nothing below {_HU_MIN_BELOW:g}: no "
            "air or fat, so these are not Hounsfield units. Raw scanner values stored as "
            "HU + 1024 need 1024 subtracted (or the NIfTI scl_inter set to -1024)"
        )


def _check_bone_hu(ct: np.ndarray, labels: np.ndarray, path: Path) -> None:
    """The segmented bone must look like bone: catches an all-air CT, a CT that is not the scan
    the masks were made from, and offset HU."""
    bone = np.isin(labels, np.fromiter(L.BONE_IDS, np.uint8))
    if bone.sum() < 50:
        return
    med = float(np.median(ct[bone]))
    lo, hi = _BONE_MEDIAN_HU
    if not lo <= med <= hi:
        raise PatientError(
            f"{path}: the CT inside the bone masks has median {med:g} HU, outside the "
            f"{lo:g}-{hi:g} HU of bone in Hounsfield units: the CT is empty (all air), not in HU, "
            "or not the scan the masks were segmented from"
        )


def _check_target(labels: np.ndarray, affine: np.ndarray, target: str, folder: Path) -> None:
    vid = L.LUMBAR_VERTEBRAE[target]
    m = labels == vid
    if not m.any():
        raise PatientError(
            f"{folder}: target vertebra {target} is not in the label map; choose one of "
            f"{[lv for lv, i in L.LUMBAR_VERTEBRAE.items() if (labels == i).any()]}"
        )
    edges = []
    for ax, side in ((0, "x"), (1, "y"), (2, "z")):
        first = np.take(m, 0, axis=ax).any()
        last = np.take(m, m.shape[ax] - 1, axis=ax).any()
        edges += [f"first {side} slice"] * bool(first) + [f"last {side} slice"] * bool(last)
    if edges:
        raise PatientError(
            f"{folder}: target vertebra {target} touches the field of view's edge "
            f"({', '.join(edges)}): the scan cuts it, so its centre and trajectories would be "
            "wrong; use a scan that covers the whole vertebra or another target"
        )
    ml = float(m.sum()) * abs(np.linalg.det(affine[:3, :3])) * 1e6
    lo, hi = _VERTEBRA_ML
    if not lo <= ml <= hi:
        raise PatientError(
            f"{folder}: target vertebra {target} has {ml:.1f} mL, outside the {lo:g}-{hi:g} mL of "
            "an adult lumbar vertebra: check the voxel size (pixdim, xyzt_units) in the NIfTI "
            "headers and that the mask is binary"
        )


def _content_seed(ct: np.ndarray, labels: np.ndarray, affine: np.ndarray) -> int:
    """Stable 31-bit seed from the subject's content (CT, labels, grid), not its folder name;
    a strided sample of large volumes keeps it cheap."""
    step = max(1, ct.size // _HASH_VOXELS)
    h = hashlib.blake2b(digest_size=8)
    h.update(np.asarray(ct.shape, np.int64).tobytes())
    h.update(np.round(affine, 9).tobytes())
    h.update(np.ascontiguousarray(ct.reshape(-1)[::step]).tobytes())
    h.update(np.ascontiguousarray(labels.reshape(-1)[::step]).tobytes())
    return int.from_bytes(h.digest(), "little") & 0x7FFFFFFF


# ----------------------------------------------------------------------------- labels


def _read_combined(f: _Nifti, ct_file: _Nifti) -> np.ndarray:
    f.same_grid(ct_file)
    raw, _ = f.read()
    if np.issubdtype(raw.dtype, np.floating):
        if not np.isfinite(raw).all() or (raw != np.round(raw)).any():
            raise PatientError(
                f"{f.path}: a combined label map must hold integer class ids; it has "
                "fractional or non-finite values (a probability map? threshold it first)"
            )
    lab = np.asarray(raw)
    ids = np.unique(lab)
    unknown = sorted(set(ids.astype(np.int64).tolist()) - set(L.LABELS) - {0})
    if unknown:
        raise PatientError(
            f"{f.path}: label ids {unknown[:20]} are not TotalSegmentator v2 / sonogym ids "
            "(see sonogym.anatomy.labels); convert v1 ids to v2 first"
        )
    return lab.astype(np.uint8)


def _mask(f: _Nifti, threshold: float | None) -> np.ndarray:
    """Foreground of one per-class mask file (binary, or thresholded when asked)."""
    m, _ = f.read()
    if threshold is not None:
        if np.issubdtype(m.dtype, np.floating) and not np.isfinite(m).all():
            raise PatientError(f"{f.path}: mask has NaN/inf values; fix the file")
        return m >= threshold
    fg = m != 0
    vals = m[fg]
    if vals.size and (vals.min() != vals.max() or not vals[0] > 0 or (m < 0).any()):
        seen = np.unique(vals[:: max(1, vals.size // 100_000)])[:5].tolist()
        seen = ([0] if vals.size < m.size else []) + seen
        raise PatientError(
            f"{f.path}: mask is not binary (values such as {seen}): a probability or "
            "multi-label map. Threshold it yourself, or pass mask_threshold (e.g. 0.5: a voxel "
            "belongs to the class where the value is >= it)"
        )
    return fg


def _combine_masks(
    seg_dir: Path, ct_file: _Nifti, threshold: float | None, shape: tuple[int, int, int]
) -> tuple[np.ndarray, list[str]]:
    """One label map, in canonical RAS voxel order of ``shape`` (the reoriented CT's), from
    per-class masks on the CT's file grid. Soft-tissue classes first, so organs and bones
    painted later win where masks overlap."""
    files = sorted(p for p in seg_dir.iterdir() if p.name.endswith((".nii", ".nii.gz")))
    if not files:
        raise FileNotFoundError(f"{seg_dir} holds no .nii/.nii.gz masks")
    order = [L.BODY_TRUNC, L.SUBCUTANEOUS_FAT, L.SKIN]
    by_id, ignored = {}, []
    for f in files:
        stem = f.name.removesuffix(".gz").removesuffix(".nii")
        if stem not in L.LABEL_IDS:
            ignored.append(stem)
            continue
        i = L.LABEL_IDS[stem]
        if i in by_id:
            raise PatientError(f"both {by_id[i]} and {f} exist; keep one")
        by_id[i] = f
    labels = np.zeros(shape, np.uint8)  # not the file's shape: masks are read reoriented
    for i in order + sorted(k for k in by_id if k not in order):
        if i not in by_id:
            continue
        f = _Nifti(by_id[i], "mask")
        f.same_grid(ct_file)  # before reading: a forged header cannot make us allocate
        labels[_mask(f, threshold)] = i
    return labels, ignored


# ----------------------------------------------------------------------------- resampling


def _to_isotropic(ct, labels, affine, spacing, folder):
    lin = affine[:3, :3]
    sp = np.linalg.norm(lin, axis=0)
    aligned = np.abs(lin - np.diag(np.diag(lin))).max() < 1e-9 and (np.diag(lin) > 0).all()
    if spacing is None:
        if aligned and np.allclose(sp, sp[0], rtol=1e-6):
            return ct, labels, affine
        spacing = float(sp.min())
    if aligned and np.allclose(sp, spacing, rtol=1e-6, atol=1e-9):
        return ct, labels, affine
    corners = np.array(
        [
            [i, j, k, 1.0]
            for i in (0, ct.shape[0] - 1)
            for j in (0, ct.shape[1] - 1)
            for k in (0, ct.shape[2] - 1)
        ]
    )
    world = (affine @ corners.T).T[:, :3]
    lo, hi = world.min(0), world.max(0)
    shape = tuple(int(np.floor((hi[i] - lo[i]) / spacing + 1e-6)) + 1 for i in range(3))
    _check_memory(
        math.prod(shape) * _BYTES_PER_VOXEL,
        f"{folder} resampled to {spacing * 1e3:g} mm ({shape[0]} x {shape[1]} x {shape[2]} voxels)",
    )
    new = np.diag([spacing, spacing, spacing, 1.0])
    new[:3, 3] = lo
    m = np.linalg.inv(affine) @ new  # new voxel -> old voxel
    if aligned:  # separable: per-axis index maps, much faster than a general affine transform
        coords = [m[a, a] * np.arange(shape[a]) + m[a, 3] for a in range(3)]
        return (*_separable_resample(ct, labels, coords), new)
    ct_r = ndimage.affine_transform(ct, m[:3, :3], m[:3, 3], shape, order=1, cval=-1024.0)
    lab_r = ndimage.affine_transform(labels, m[:3, :3], m[:3, 3], shape, order=0, cval=0)
    return ct_r.astype(np.float32), lab_r.astype(np.uint8), new


def _separable_resample(ct, labels, coords):
    """Trilinear CT and nearest labels at old-voxel coordinates ``coords`` (one 1-D array per
    axis), the same values as ``ndimage.affine_transform`` with order 1 / 0."""
    out = ct
    for a, c in enumerate(coords):
        n = ct.shape[a]
        c = np.clip(c, 0, n - 1)
        i0 = np.minimum(np.floor(c).astype(np.int64), n - 2) if n > 1 else np.zeros(len(c), int)
        w = (c - i0).astype(np.float32) if n > 1 else np.zeros(len(c), np.float32)
        shape = [1, 1, 1]
        shape[a] = -1
        w = w.reshape(shape)
        lo_ = np.take(out, i0, axis=a)
        hi_ = np.take(out, np.minimum(i0 + 1, n - 1), axis=a)
        out = lo_ + w * (hi_ - lo_)
    # floor(c + 0.5): ndimage's nearest rounds ties up
    idx = [
        np.clip(np.floor(c + 0.5).astype(np.int64), 0, n - 1)
        for c, n in zip(coords, labels.shape, strict=True)
    ]
    lab = labels[np.ix_(*idx)]
    return out.astype(np.float32, copy=False), lab


# ----------------------------------------------------------------------------- soft tissue


def _within(inside: np.ndarray, h: float, radius: float) -> np.ndarray:
    """Inside voxels whose centre lies within ``radius`` (m) of an outside voxel centre: exact
    Euclidean distance by separable minimum over windows of +-radius (cheap for small radii).
    Outside the array does not count as outside (a body cut by the field of view has no skin
    there)."""
    r = int(radius / h + 1e-6)
    d = np.where(inside, np.float32(np.inf), np.float32(0.0))
    for ax in range(3):
        out = d.copy()
        n = d.shape[ax]
        for k in range(1, min(r, n - 1) + 1):
            w = np.float32((k * h) ** 2)
            a = [slice(None)] * 3
            b = [slice(None)] * 3
            a[ax], b[ax] = slice(k, None), slice(None, n - k)
            np.minimum(out[tuple(a)], d[tuple(b)] + w, out=out[tuple(a)])
            np.minimum(out[tuple(b)], d[tuple(a)] + w, out=out[tuple(b)])
        d = out
    return inside & (d <= np.float32(radius**2 * (1 + 1e-6)))


def _complete_soft_tissue(labels: np.ndarray, ct: np.ndarray, zooms) -> np.ndarray:
    """Add body_trunc, skin and subcutaneous fat where the label map lacks them, on the grid the
    patient will use (isotropic spacing ``zooms``, m)."""
    h = float(zooms[0])
    labels = labels.copy()
    if not (labels == L.BODY_TRUNC).any():
        body = ct > _BODY_HU
        lab, n = ndimage.label(body)
        if n:
            sizes = np.bincount(lab.reshape(-1))
            body = lab == (int(np.argmax(sizes[1:])) + 1)
        del lab
        body = ndimage.binary_fill_holes(body) | (labels > 0)
        labels[body & (labels == 0)] = L.BODY_TRUNC
        del body
    inside = labels > 0
    if not (labels == L.SUBCUTANEOUS_FAT).any():
        # Depth on a grid of <= 3 mm: the 40 mm cut-off does not need more.
        f = max(1, int(_FAT_DEPTH_GRID / h + 1e-6))
        coarse = inside[::f, ::f, ::f]
        depth = ndimage.distance_transform_edt(coarse, sampling=h * f)
        shallow = depth <= _FAT_MAX_DEPTH
        idx = [
            np.minimum(np.arange(n) // f, shallow.shape[a] - 1) for a, n in enumerate(labels.shape)
        ]
        fat = (labels == L.BODY_TRUNC) & (ct >= _FAT_HU[0]) & (ct <= _FAT_HU[1])
        fat &= shallow[np.ix_(*idx)]
        labels[fat] = L.SUBCUTANEOUS_FAT
        del fat
    if not (labels == L.SKIN).any():
        # Skin: voxels whose centre lies within 2 mm of the surface (halfway between inside and
        # outside voxel centres), at least the outermost layer on coarse grids.
        skin = _within(inside, h, max(_SKIN_THICKNESS + h / 2, h))
        labels[skin & np.isin(labels, [L.BODY_TRUNC, L.SUBCUTANEOUS_FAT])] = L.SKIN
    return labels


# ----------------------------------------------------------------------------- writing


def _save_nifti(img: nib.Nifti1Image, path: Path) -> None:
    """``img`` as a gzipped NIfTI at ``path``, written atomically (temporary file + rename: a
    killed write never leaves a truncated file under the final name)."""
    atomic_write_bytes(path, gzip.compress(img.to_bytes(), compresslevel=1, mtime=0))


def save_totalsegmentator(patient: Patient, folder: str | Path, combined: bool = False) -> Path:
    """Write ``patient`` as ct.nii.gz + segmentations/<class>.nii.gz (or one combined map) and a
    ``sonogym.json`` with its name and provenance, each file atomically. Loading the folder gives
    the same patient."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    aff = patient.affine.copy()
    aff[:3, :] *= 1e3  # NIfTI in millimetres
    ct = patient.ct.numpy()
    integral = bool(np.all(ct == np.round(ct))) and ct.min() >= -32768 and ct.max() <= 32767
    ct_img = nib.Nifti1Image(ct.astype(np.int16 if integral else np.float32), aff)
    ct_img.header.set_xyzt_units("mm", "sec")
    _save_nifti(ct_img, folder / "ct.nii.gz")
    labels = patient.labels.numpy()
    if combined:
        img = nib.Nifti1Image(labels, aff)
        img.header.set_xyzt_units("mm", "sec")
        _save_nifti(img, folder / "combined_label_map.nii.gz")
    else:
        seg = folder / "segmentations"
        seg.mkdir(exist_ok=True)
        for i in np.unique(labels).tolist():
            if i == 0:
                continue
            img = nib.Nifti1Image((labels == i).astype(np.uint8), aff)
            img.header.set_xyzt_units("mm", "sec")
            _save_nifti(img, seg / f"{L.LABELS[i]}.nii.gz")
    atomic_write_text(
        folder / "sonogym.json",
        json.dumps({"name": patient.name, "meta": patient.meta}, indent=1, default=str),
    )
    return folder
