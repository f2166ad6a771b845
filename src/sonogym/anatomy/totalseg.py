"""Read and write patients in the TotalSegmentator folder layout.

A subject folder holds ``ct.nii.gz`` (or ``ct.nii``) and either ``segmentations/<class>.nii.gz``
(one binary mask per TotalSegmentator v2 class name; project names such as ``body_trunc``,
``subcutaneous_fat``, ``intervertebral_discs``, ``skin`` and ``spinal_canal`` are read too) or
one combined label map ``combined_label_map.nii.gz`` with the ids of ``sonogym.anatomy.labels``.

Loading reorients to canonical RAS, converts millimetres to metres, and resamples onto an
axis-aligned isotropic grid when the file's grid is anisotropic or oblique (CT trilinear, labels
nearest). Missing body, skin and fat labels are derived from the CT.
"""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import torch
from scipy import ndimage

from sonogym.anatomy import labels as L
from sonogym.anatomy.patient import Patient, PatientError

COMBINED_NAMES = ("combined_label_map", "labels")
_FAT_HU = (-190.0, -30.0)  # HU window of adipose tissue
_FAT_MAX_DEPTH = 0.04  # m: fat within this depth of the body surface counts as subcutaneous
_SKIN_THICKNESS = 0.002  # m
_BODY_HU = -500.0


def _nifti(folder: Path, stem: str) -> Path | None:
    for ext in (".nii.gz", ".nii"):
        if (folder / f"{stem}{ext}").exists():
            return folder / f"{stem}{ext}"
    return None


def _unit_scale(img: nib.Nifti1Image) -> float:
    unit = img.header.get_xyzt_units()[0]
    return {"meter": 1.0, "mm": 1e-3, "micron": 1e-6}.get(unit, 1e-3)


def _read(path: Path, what: str) -> nib.Nifti1Image:
    try:
        img = nib.load(str(path))
    except Exception as e:  # nibabel raises several types for broken files
        raise PatientError(f"cannot read {what} {path}: {e}") from e
    shape = img.shape
    if len(shape) == 4 and shape[3] == 1:
        img = img.slicer[..., 0]
    if len(img.shape) != 3:
        raise PatientError(f"{path}: {what} must be a 3-D volume, got shape {shape}")
    return nib.as_closest_canonical(img)


def load_totalsegmentator(
    folder: str | Path,
    spacing: float | None = 0.001,
    target: str | None = None,
    name: str | None = None,
) -> Patient:
    """Load a TotalSegmentator subject folder as a :class:`Patient`.

    Args:
        folder: subject folder with ``ct.nii[.gz]`` and ``segmentations/`` or a combined map.
        spacing: isotropic voxel size in metres to resample to; ``None`` keeps the file's grid
            when it is already isotropic and axis-aligned (else uses its finest spacing).
        target: a vertebra ("L4") that must be present, else :class:`PatientError`.
        name: patient name (default: the folder name).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"patient folder {folder} does not exist")
    ct_path = _nifti(folder, "ct")
    if ct_path is None:
        raise FileNotFoundError(
            f"no CT in {folder}: expected {folder / 'ct.nii.gz'} (TotalSegmentator layout)"
        )
    ct_img = _read(ct_path, "CT")
    ct = np.asarray(ct_img.dataobj, dtype=np.float32)
    if np.isnan(ct).any():
        raise PatientError(f"{ct_path}: CT contains NaN values; replace them (e.g. by -1024 HU)")
    ignored: list[str] = []
    comb = next((p for s in COMBINED_NAMES if (p := _nifti(folder, s)) is not None), None)
    seg_dir = folder / "segmentations"
    if comb is not None:
        img = _read(comb, "label map")
        _check_grid(img, ct_img, comb, ct_path)
        labels = np.asarray(img.dataobj).astype(np.int64)
        unknown = sorted(set(np.unique(labels).tolist()) - set(L.LABELS) - {0})
        if unknown:
            raise PatientError(
                f"{comb}: label ids {unknown} are not TotalSegmentator v2 / sonogym ids "
                "(see sonogym.anatomy.labels); convert v1 ids to v2 first"
            )
        labels = labels.astype(np.uint8)
    elif seg_dir.is_dir():
        labels, ignored = _combine_masks(seg_dir, ct_img, ct_path)
    else:
        raise FileNotFoundError(
            f"no labels in {folder}: expected {seg_dir}/<class>.nii.gz or "
            f"{folder / 'combined_label_map.nii.gz'}"
        )
    labels = _complete_soft_tissue(labels, ct, ct_img.header.get_zooms()[:3])
    affine = ct_img.affine.copy()
    affine[:3, :] *= _unit_scale(ct_img)
    ct, labels, affine = _to_isotropic(ct, labels, affine, spacing)
    meta = {"source": str(folder)}
    if ignored:
        meta["ignored_masks"] = ignored
    info = folder / "sonogym.json"
    if info.exists():
        meta = {**json.loads(info.read_text()).get("meta", {}), **meta}
    patient = Patient(
        ct=torch.from_numpy(np.ascontiguousarray(ct, dtype=np.float32)),
        labels=torch.from_numpy(np.ascontiguousarray(labels, dtype=np.uint8)),
        affine=affine,
        name=name or folder.name,
        meta=meta,
    )
    if target is not None and not patient.has(L.label_id(target)):
        raise PatientError(
            f"{folder}: target vertebra {target} is not in the label map; choose one of "
            f"{[lv for lv, i in L.LUMBAR_VERTEBRAE.items() if patient.has(i)]}"
        )
    return patient


def _check_grid(img, ct_img, path, ct_path) -> None:
    if img.shape != ct_img.shape or not np.allclose(img.affine, ct_img.affine, atol=1e-3):
        raise PatientError(
            f"{path}: label grid (shape {img.shape}) differs from the CT grid {ct_path} "
            f"(shape {ct_img.shape}); resample the labels onto the CT grid"
        )


def _combine_masks(seg_dir: Path, ct_img, ct_path) -> tuple[np.ndarray, list[str]]:
    """One label map from per-class masks. Soft-tissue classes first, so organs and bones
    painted later win where masks overlap."""
    files = sorted(p for p in seg_dir.iterdir() if p.name.endswith((".nii", ".nii.gz")))
    if not files:
        raise FileNotFoundError(f"{seg_dir} holds no .nii/.nii.gz masks")
    order = [L.BODY_TRUNC, L.SUBCUTANEOUS_FAT, L.SKIN]
    by_id, ignored = {}, []
    for f in files:
        stem = f.name.removesuffix(".gz").removesuffix(".nii")
        if stem in L.LABEL_IDS:
            by_id[L.LABEL_IDS[stem]] = f
        else:
            ignored.append(stem)
    labels = np.zeros(ct_img.shape, np.uint8)
    for i in order + sorted(k for k in by_id if k not in order):
        if i not in by_id:
            continue
        img = _read(by_id[i], "mask")
        _check_grid(img, ct_img, by_id[i], ct_path)
        labels[np.asarray(img.dataobj) > 0] = i
    return labels, ignored


def _complete_soft_tissue(labels: np.ndarray, ct: np.ndarray, zooms) -> np.ndarray:
    """Add body_trunc, skin and subcutaneous fat where the label map lacks them."""
    labels = labels.copy()
    if not (labels == L.BODY_TRUNC).any():
        body = ct > _BODY_HU
        lab, n = ndimage.label(body)
        if n:
            sizes = ndimage.sum(body, lab, range(1, n + 1))
            body = lab == (int(np.argmax(sizes)) + 1)
        body = ndimage.binary_fill_holes(body) | (labels > 0)
        labels[body & (labels == 0)] = L.BODY_TRUNC
    inside = labels > 0
    depth = ndimage.distance_transform_edt(inside, sampling=np.asarray(zooms, np.float64) * 1e-3)
    if not (labels == L.SUBCUTANEOUS_FAT).any():
        fat = (
            (labels == L.BODY_TRUNC)
            & (ct >= _FAT_HU[0])
            & (ct <= _FAT_HU[1])
            & (depth <= _FAT_MAX_DEPTH)
        )
        labels[fat] = L.SUBCUTANEOUS_FAT
    if not (labels == L.SKIN).any():
        soft = np.isin(labels, [L.BODY_TRUNC, L.SUBCUTANEOUS_FAT])
        labels[soft & (depth <= _SKIN_THICKNESS + 1e-6)] = L.SKIN
    return labels


def _to_isotropic(ct, labels, affine, spacing):
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
    new = np.diag([spacing, spacing, spacing, 1.0])
    new[:3, 3] = lo
    m = np.linalg.inv(affine) @ new  # new voxel -> old voxel
    ct_r = ndimage.affine_transform(ct, m[:3, :3], m[:3, 3], shape, order=1, cval=-1024.0)
    lab_r = ndimage.affine_transform(labels, m[:3, :3], m[:3, 3], shape, order=0, cval=0)
    return ct_r.astype(np.float32), lab_r.astype(np.uint8), new


def save_totalsegmentator(patient: Patient, folder: str | Path, combined: bool = False) -> Path:
    """Write ``patient`` as ct.nii.gz + segmentations/<class>.nii.gz (or one combined map) and a
    ``sonogym.json`` with its name and provenance. Loading the folder gives the same patient."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    aff = patient.affine.copy()
    aff[:3, :] *= 1e3  # NIfTI in millimetres
    ct = patient.ct.numpy()
    integral = bool(np.all(ct == np.round(ct))) and ct.min() >= -32768 and ct.max() <= 32767
    ct_img = nib.Nifti1Image(ct.astype(np.int16 if integral else np.float32), aff)
    ct_img.header.set_xyzt_units("mm", "sec")
    nib.save(ct_img, str(folder / "ct.nii.gz"))
    labels = patient.labels.numpy()
    if combined:
        img = nib.Nifti1Image(labels, aff)
        img.header.set_xyzt_units("mm", "sec")
        nib.save(img, str(folder / "combined_label_map.nii.gz"))
    else:
        seg = folder / "segmentations"
        seg.mkdir(exist_ok=True)
        for i in np.unique(labels).tolist():
            if i == 0:
                continue
            img = nib.Nifti1Image((labels == i).astype(np.uint8), aff)
            img.header.set_xyzt_units("mm", "sec")
            nib.save(img, str(seg / f"{L.LABELS[i]}.nii.gz"))
    (folder / "sonogym.json").write_text(
        json.dumps({"name": patient.name, "meta": patient.meta}, indent=1, default=str)
    )
    return folder
