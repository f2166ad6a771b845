"""Any valid storage of a subject loads to the same anatomy: every axis order and flip of the
voxel array (48 orientations), isotropic and anisotropic voxels, and every CT voxel type a
scanner or a converter writes."""

import itertools
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from scipy import ndimage

from sonogym.anatomy import PatientError, load_totalsegmentator

SUBJECT = Path(__file__).resolve().parents[1] / "data" / "totalsegmentator_example"
MASKS = ("vertebrae_L3", "vertebrae_L4", "vertebrae_L5", "autochthon_left", "autochthon_right")
ORIENTATIONS = [
    (perm, flips)
    for perm in itertools.permutations(range(3))
    for flips in itertools.product((False, True), repeat=3)
]
# CT voxel types as files hold them: (numpy type, slope, intercept); uint16 stores HU + 1024
CT_TYPES = [
    (np.int16, 1.0, 0.0),
    (np.int32, 1.0, 0.0),
    (np.float32, 1.0, 0.0),
    (np.float64, 1.0, 0.0),
    (np.uint16, 1.0, -1024.0),
]
SPACING = 0.003  # m: the subject's own voxel size, so the reference is read without resampling


@pytest.fixture(scope="module")
def lumbar_crop():
    """The shipped subject's CT and a few masks, cropped to L3-L5 with a margin (RAS arrays,
    affine in mm), and the L4 centre loaded from the original folder."""
    ct_img = nib.load(SUBJECT / "ct.nii.gz")
    assert nib.aff2axcodes(ct_img.affine) == ("R", "A", "S")
    masks = {
        m: np.asanyarray(nib.load(SUBJECT / "segmentations" / f"{m}.nii.gz").dataobj) for m in MASKS
    }
    spine = sum(masks[m] for m in MASKS[:3]) > 0
    lo = np.argwhere(spine).min(0) - (12, 20, 6)
    hi = np.argwhere(spine).max(0) + (12, 20, 6)
    lo, hi = np.maximum(lo, 0), np.minimum(hi + 1, spine.shape)
    box = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))
    aff = ct_img.affine.copy()
    aff[:3, 3] += aff[:3, :3] @ lo
    ct = np.asanyarray(ct_img.dataobj)[box].astype(np.float64)
    ref = load_totalsegmentator(SUBJECT, spacing=SPACING, target="L4")
    return ct, {m: a[box] for m, a in masks.items()}, aff, ref.landmarks.vertebra("L4").centre


def _store(a: np.ndarray, aff: np.ndarray, perm, flips):
    """The same voxels in another array order: flip then permute the axes, affine to match."""
    aff = aff.copy()
    for ax in range(3):
        if flips[ax]:
            a = np.flip(a, ax)
            f = np.eye(4)
            f[ax, ax], f[ax, 3] = -1.0, a.shape[ax] - 1
            aff = aff @ f
    p = np.eye(4)
    p[:3, :3] = np.eye(3)[:, list(perm)]
    return np.ascontiguousarray(np.transpose(a, perm)), aff @ p


def _anisotropic(ct, masks, aff, zoom_mm=(2.0, 3.5, 4.5)):
    """Resampled to voxels of ``zoom_mm`` (CT linear, masks nearest)."""
    f = [3.0 / z for z in zoom_mm]
    aff = aff.copy()
    aff[:3, :3] = aff[:3, :3] @ np.diag([z / 3.0 for z in zoom_mm])
    return (
        ndimage.zoom(ct, f, order=1),
        {m: ndimage.zoom(a, f, order=0) for m, a in masks.items()},
        aff,
    )


def _write(folder: Path, ct, masks, aff, perm, flips, ct_type):
    dtype, slope, inter = ct_type
    (folder / "segmentations").mkdir(parents=True)
    stored, a = _store((ct - inter) / slope, aff, perm, flips)
    img = nib.Nifti1Image(np.round(stored).astype(dtype), a)
    img.header.set_slope_inter(slope, inter)
    nib.save(img, folder / "ct.nii.gz")
    for m, arr in masks.items():
        stored, a = _store(arr, aff, perm, flips)
        nib.save(
            nib.Nifti1Image(stored.astype(np.uint8), a), folder / "segmentations" / f"{m}.nii.gz"
        )


@pytest.mark.parametrize("anisotropic", [False, True], ids=["3mm", "2x3.5x4.5mm"])
def test_every_orientation_spacing_and_ct_type_gives_the_same_l4(
    lumbar_crop, tmp_path, anisotropic
):
    ct, masks, aff, centre = lumbar_crop
    if anisotropic:
        ct, masks, aff = _anisotropic(ct, masks, aff)
    for i, (perm, flips) in enumerate(ORIENTATIONS):
        folder = tmp_path / f"o{i}"
        _write(folder, ct, masks, aff, perm, flips, CT_TYPES[i % len(CT_TYPES)])
        p = load_totalsegmentator(folder, spacing=SPACING, target="L4")
        got = p.landmarks.vertebra("L4").centre
        err = np.linalg.norm(got - centre)
        assert err <= SPACING, f"axes {perm}, flips {flips}: L4 centre {err * 1e3:.2f} mm off"


def test_a_mask_whose_origin_is_off_names_the_offset(lumbar_crop, tmp_path):
    ct, masks, aff, _ = lumbar_crop
    _write(tmp_path / "s", ct, masks, aff, (0, 1, 2), (False,) * 3, CT_TYPES[0])
    moved = aff.copy()
    moved[0, 3] += 30.0
    path = tmp_path / "s" / "segmentations" / "vertebrae_L4.nii.gz"
    nib.save(nib.Nifti1Image(masks["vertebrae_L4"].astype(np.uint8), moved), path)
    with pytest.raises(PatientError, match=r"origin is 30 mm away from the CT's"):
        load_totalsegmentator(tmp_path / "s", spacing=SPACING)
