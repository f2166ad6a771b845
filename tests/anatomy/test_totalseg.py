import math

import nibabel as nib
import numpy as np
import pytest
import torch
from scipy import ndimage

from sonogym.anatomy import PatientError, load_totalsegmentator, save_totalsegmentator
from sonogym.anatomy import labels as L


@pytest.mark.parametrize("combined", [False, True])
def test_save_then_load_gives_the_same_patient(small_phantom, tmp_path, combined):
    save_totalsegmentator(small_phantom, tmp_path / "s", combined=combined)
    assert (tmp_path / "s" / "ct.nii.gz").exists()
    if not combined:
        assert (tmp_path / "s" / "segmentations" / "vertebrae_L4.nii.gz").exists()
    q = load_totalsegmentator(tmp_path / "s", spacing=None)
    assert torch.equal(q.ct, small_phantom.ct)
    assert torch.equal(q.labels, small_phantom.labels)
    assert np.allclose(q.affine, small_phantom.affine)
    assert q.meta["seed"] == 0


def test_a_killed_save_leaves_no_truncated_file(small_phantom, tmp_path, monkeypatch):
    import os

    folder = tmp_path / "s"
    save_totalsegmentator(small_phantom, folder)
    before = (folder / "ct.nii.gz").read_bytes()

    def killed(fd):  # the process dies with the new CT's bytes written, before the rename
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "fsync", killed)
    with pytest.raises(KeyboardInterrupt):
        save_totalsegmentator(small_phantom, folder)
    monkeypatch.undo()
    assert (folder / "ct.nii.gz").read_bytes() == before  # the old file, whole
    assert not [p.name for p in folder.rglob("*") if ".tmp" in p.name]
    assert torch.equal(load_totalsegmentator(folder, spacing=None).ct, small_phantom.ct)


def _write_lps_anisotropic(p, folder, zoom=(2.0, 2.0, 3.0)):
    """Resample p onto an anisotropic grid stored in LPS orientation, per-class masks."""
    sp = p.spacing[0] * 1e3
    factors = [sp / z for z in zoom]
    ct = ndimage.zoom(p.ct.numpy(), factors, order=1)
    lab = ndimage.zoom(p.labels.numpy(), factors, order=0)
    ct, lab = ct[::-1, ::-1], lab[::-1, ::-1]  # RAS -> LPS voxel order
    n = ct.shape
    lo = p.origin * 1e3
    aff = np.diag([-zoom[0], -zoom[1], zoom[2], 1.0])
    aff[:3, 3] = [lo[0] + (n[0] - 1) * zoom[0], lo[1] + (n[1] - 1) * zoom[1], lo[2]]
    folder.mkdir()
    nib.save(nib.Nifti1Image(ct.astype(np.int16), aff), folder / "ct.nii.gz")
    (folder / "segmentations").mkdir()
    for i in np.unique(lab).tolist():
        if i:
            m = (lab == i).astype(np.uint8)
            nib.save(nib.Nifti1Image(m, aff), folder / "segmentations" / f"{L.LABELS[i]}.nii.gz")


def test_lps_anisotropic_file_loads_to_the_same_anatomy(small_phantom, tmp_path):
    _write_lps_anisotropic(small_phantom, tmp_path / "lps")
    q = load_totalsegmentator(tmp_path / "lps", spacing=0.002, target="L4")
    assert np.allclose(q.spacing, 0.002)
    a, b = small_phantom.landmarks, q.landmarks
    for lv in ("L2", "L4"):
        fa, fb = a.vertebra(lv), b.vertebra(lv)
        assert np.linalg.norm(fa.centre - fb.centre) < 0.002
        assert math.degrees(math.acos(min(1, fa.anterior @ fb.anterior))) < 4
        ta, tb = a.trajectory(lv, "right"), b.trajectory(lv, "right")
        assert np.linalg.norm(ta.entry - tb.entry) < 0.005
    x, z = torch.tensor([0.0, 0.04]), torch.tensor([0.0, 0.02])
    assert (small_phantom.skin.height(x, z) - q.skin.height(x, z)).abs().max() < 0.0025


def test_missing_body_fat_and_skin_are_derived_from_ct(small_phantom, tmp_path):
    keep = {28, 29, 27, 86, 87}
    labels = small_phantom.labels.clone()
    labels[~torch.isin(labels, torch.tensor(sorted(keep), dtype=torch.uint8))] = 0
    from sonogym.anatomy import Patient

    bare = Patient(ct=small_phantom.ct, labels=labels, affine=small_phantom.affine, name="bare")
    save_totalsegmentator(bare, tmp_path / "bare")
    q = load_totalsegmentator(tmp_path / "bare", spacing=None)
    present = set(torch.unique(q.labels).tolist())
    assert {L.BODY_TRUNC, L.SUBCUTANEOUS_FAT, L.SKIN} <= present
    # derived fat overlaps the phantom's own fat layer well
    fat_true = small_phantom.labels == L.SUBCUTANEOUS_FAT
    fat = q.labels == L.SUBCUTANEOUS_FAT
    dice = 2 * (fat & fat_true).sum() / (fat.sum() + fat_true.sum())
    assert dice > 0.6
    # the derived skin lies at the body surface found by the phantom's skin surface
    assert (q.skin.height(torch.zeros(1), torch.zeros(1)) - small_phantom.skin.height(
        torch.zeros(1), torch.zeros(1))).abs().item() < 0.002  # fmt: skip


def _folder_with(tmp_path, ct, masks, aff=None):
    aff = np.diag([2.0, 2.0, 2.0, 1.0]) if aff is None else aff
    f = tmp_path / "subj"
    (f / "segmentations").mkdir(parents=True)
    if ct is not None:
        nib.save(nib.Nifti1Image(ct, aff), f / "ct.nii.gz")
    for name, (m, maff) in masks.items():
        nib.save(nib.Nifti1Image(m, aff if maff is None else maff), f / "segmentations" / name)
    return f


def test_bad_inputs_raise_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_totalsegmentator(tmp_path / "nope")
    ct = np.full((24, 24, 24), -1000, np.int16)
    ct[3:21, 3:21, 3:21] = 40
    m = np.zeros((24, 24, 24), np.uint8)
    m[5:18, 5:18, 5:18] = 1  # 17.6 mL at 2 mm: an adult vertebra's volume
    ct[m > 0] = 300
    f = _folder_with(tmp_path, None, {"vertebrae_L4.nii.gz": (m, None)})
    with pytest.raises(FileNotFoundError, match="ct.nii.gz"):
        load_totalsegmentator(f)
    nib.save(nib.Nifti1Image(ct, np.diag([2.0, 2.0, 2.0, 1.0])), f / "ct.nii.gz")
    nib.save(
        nib.Nifti1Image(m[:10], np.diag([2.0, 2.0, 2.0, 1.0])), f / "segmentations" / "liver.nii.gz"
    )
    with pytest.raises(PatientError, match="differs from the CT grid"):
        load_totalsegmentator(f)
    (f / "segmentations" / "liver.nii.gz").unlink()
    with pytest.raises(PatientError, match="target vertebra L3"):
        load_totalsegmentator(f, spacing=None, target="L3")
    assert load_totalsegmentator(f, spacing=None, target="L4").has("L4")
    nan_ct = ct.astype(np.float32)
    nan_ct[0, 0, 0] = np.nan
    nib.save(nib.Nifti1Image(nan_ct, np.diag([2.0, 2.0, 2.0, 1.0])), f / "ct.nii.gz")
    with pytest.raises(PatientError, match="NaN"):
        load_totalsegmentator(f)
    nib.save(nib.Nifti1Image(np.zeros((20, 20, 20, 2), np.int16), np.eye(4)), f / "ct.nii.gz")
    with pytest.raises(PatientError, match="3-D"):
        load_totalsegmentator(f)


def test_combined_map_with_foreign_ids_is_refused(tmp_path):
    f = tmp_path / "c"
    f.mkdir()
    nib.save(nib.Nifti1Image(np.full((8, 8, 8), -1000, np.int16), np.eye(4)), f / "ct.nii.gz")
    lab = np.zeros((8, 8, 8), np.uint8)
    lab[2, 2, 2] = 200
    nib.save(nib.Nifti1Image(lab, np.eye(4)), f / "combined_label_map.nii.gz")
    with pytest.raises(PatientError, match="200"):
        load_totalsegmentator(f)
