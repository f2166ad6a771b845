"""Hostile or careless subject folders: each is refused with a PatientError naming the file and
the fix, before anything large is allocated. Built from a small crop of the real subject (L3-L5
region, 3 mm) so each load takes a fraction of a second."""

import gzip
import os
import shutil
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import torch

from sonogym.anatomy import LandmarkError, Patient, PatientError, load_totalsegmentator
from sonogym.anatomy import totalseg as TS
from sonogym.envs.patients import resolve_patients
from sonogym.ultrasound.slicer import speckle_seed

SUBJECT = Path(__file__).resolve().parents[1] / "data" / "totalsegmentator_example"
MASKS = ("vertebrae_L3", "vertebrae_L4", "vertebrae_L5", "autochthon_left", "autochthon_right")


def _img(path):
    img = nib.load(str(path))
    return np.asarray(img.dataobj), img.affine


@pytest.fixture(scope="module")
def crop(tmp_path_factory) -> Path:
    """The real subject cropped to x 35-85, y 10-60, z 40-80 (L4 whole, 3 mm voxels)."""
    out = tmp_path_factory.mktemp("crop") / "subj"
    (out / "segmentations").mkdir(parents=True)
    box = (slice(35, 85), slice(10, 60), slice(40, 80))
    ct, aff = _img(SUBJECT / "ct.nii.gz")
    aff = aff.copy()
    aff[:3, 3] += aff[:3, :3] @ [b.start for b in box]
    nib.save(nib.Nifti1Image(ct[box].astype(np.int16), aff), out / "ct.nii.gz")
    for name in MASKS:
        m, _ = _img(SUBJECT / "segmentations" / f"{name}.nii.gz")
        nib.save(
            nib.Nifti1Image(m[box].astype(np.uint8), aff), out / "segmentations" / f"{name}.nii.gz"
        )
    return out


@pytest.fixture
def subj(crop, tmp_path) -> Path:
    return Path(shutil.copytree(crop, tmp_path / "subj"))


def _rewrite(path, fn=None, affine=None, dtype=None, units=None):
    data, aff = _img(path)
    data = fn(data) if fn else data
    img = nib.Nifti1Image(data.astype(dtype) if dtype else data, aff if affine is None else affine)
    if units:
        img.header.set_xyzt_units(units)
    nib.save(img, path)


def test_the_crop_loads_as_is(subj):
    p = load_totalsegmentator(subj, spacing=None, target="L4")
    assert p.has("L4") and p.landmarks.trajectory("L4", "right").radius >= 0.0015


def test_probability_masks_need_a_threshold(subj):
    f = subj / "segmentations" / "vertebrae_L4.nii.gz"
    binary = load_totalsegmentator(subj, spacing=None).labels == 28
    _rewrite(f, lambda m: np.where(m > 0, 0.9, 0.01), dtype=np.float32)
    with pytest.raises(
        PatientError, match=r"vertebrae_L4.nii.gz: mask is not binary.*mask_threshold"
    ):
        load_totalsegmentator(subj, spacing=None)
    p = load_totalsegmentator(subj, spacing=None, mask_threshold=0.5, target="L4")
    assert torch.equal(p.labels == 28, binary)
    _rewrite(f, lambda m: m * 3, dtype=np.uint8)  # 0/3: still binary (one foreground value)
    assert torch.equal(load_totalsegmentator(subj, spacing=None).labels == 28, binary)


def test_forged_header_is_refused_before_allocating(subj):
    hdr = nib.Nifti1Header()
    hdr.set_data_shape((2000, 2000, 2000))
    hdr.set_data_dtype(np.int16)
    hdr.set_zooms((1.0, 1.0, 1.0))
    with gzip.open(subj / "ct.nii.gz", "wb") as fh:
        fh.write(hdr.binaryblock + b"\0" * 4)
    assert (subj / "ct.nii.gz").stat().st_size < 400  # a tiny file claiming 16 GB
    with pytest.raises(PatientError, match=r"ct.nii.gz: the header claims .* truncated"):
        load_totalsegmentator(subj)
    # the same forged header as a mask is refused the same way, before its grid is compared
    shutil.move(subj / "ct.nii.gz", subj / "segmentations" / "liver.nii.gz")
    shutil.copy(SUBJECT / "ct.nii.gz", subj / "ct.nii.gz")
    with pytest.raises(PatientError, match=r"liver.nii.gz: the header claims"):
        load_totalsegmentator(subj)


def test_volumes_beyond_the_memory_at_hand_are_refused(subj, monkeypatch):
    monkeypatch.setattr(TS, "_available_memory", lambda: 2**20)  # 1 MiB free
    with pytest.raises(PatientError, match=r"ct.nii.gz needs about .* GiB of memory"):
        load_totalsegmentator(subj)
    monkeypatch.setattr(TS, "_available_memory", lambda: 300 * 2**20)
    load_totalsegmentator(subj, spacing=None)  # the native grid fits
    with pytest.raises(PatientError, match=r"resampled to 0.25 mm .* crop the scan"):
        load_totalsegmentator(subj, spacing=0.00025)


def test_truncated_files_name_the_file(subj):
    for rel in ("ct.nii.gz", "segmentations/vertebrae_L4.nii.gz"):
        f = subj / rel
        good = f.read_bytes()
        f.write_bytes(good[: len(good) // 2])
        with pytest.raises(PatientError, match=rf"{f.name}.*truncated or corrupt"):
            load_totalsegmentator(subj)
        f.write_bytes(good)
    data, aff = _img(subj / "ct.nii.gz")  # uncompressed: the size check catches it first
    (subj / "ct.nii.gz").unlink()
    nib.save(nib.Nifti1Image(data, aff), subj / "ct.nii")
    raw = (subj / "ct.nii").read_bytes()
    (subj / "ct.nii").write_bytes(raw[:-1000])
    with pytest.raises(PatientError, match=r"ct.nii: the header claims"):
        load_totalsegmentator(subj)


@pytest.mark.parametrize(
    ("scale", "units", "match"),
    [
        (10 / 3, None, r"voxel size \[10.0, 10.0, 10.0\] mm"),
        (1.0, "meter", r"units 'meter'.*set xyzt_units to mm"),
        (1 / 3, None, r"target vertebra L4 has .* mL"),  # 1 mm voxels: L4 27x too small
    ],
)
def test_implausible_voxel_sizes_and_units(subj, scale, units, match):
    for f in [subj / "ct.nii.gz", *sorted((subj / "segmentations").iterdir())]:
        _, aff = _img(f)
        aff = aff.copy()
        aff[:3, :3] *= scale
        _rewrite(f, affine=aff, units=units)
    with pytest.raises(PatientError, match=match):
        load_totalsegmentator(subj, target="L4")


@pytest.mark.parametrize("spacing", [0, -0.001, 0.0001, 0.01, 1.0, float("nan"), True])
def test_spacing_option_is_checked(subj, spacing):
    with pytest.raises(PatientError, match="spacing .* 0.25-5 mm"):
        load_totalsegmentator(subj, spacing=spacing)


def test_target_cut_by_the_field_of_view(subj):
    lo = int(np.nonzero(_img(subj / "segmentations" / "vertebrae_L4.nii.gz")[0].any((0, 1)))[0][0])
    for f in [subj / "ct.nii.gz", *sorted((subj / "segmentations").iterdir())]:
        data, aff = _img(f)
        aff = aff.copy()
        aff[:3, 3] += aff[:3, 2] * (lo + 2)
        nib.save(nib.Nifti1Image(data[:, :, lo + 2 :], aff), f)
    with pytest.raises(PatientError, match="L4 touches the field of view's edge .first z slice"):
        load_totalsegmentator(subj, target="L4")
    # without a target it loads, but the cut vertebra has no landmarks
    lm = load_totalsegmentator(subj, spacing=None).landmarks
    with pytest.raises(LandmarkError, match="L4.*field of view's edge"):
        lm.vertebra("L4")


@pytest.mark.parametrize(
    ("fn", "dtype", "match"),
    [
        (lambda ct: np.clip(ct + 1024, 0, None), np.uint16, "not Hounsfield units.*1024"),
        (lambda ct: np.full_like(ct, -1000), np.int16, "median -1000 HU.*all air"),
        (lambda ct: np.where(ct > 1200, np.inf, ct), np.float32, "inf values"),
        (lambda ct: np.where(ct > 1200, np.nan, ct), np.float32, "NaN"),
    ],
)
def test_ct_values_that_are_not_hu(subj, fn, dtype, match):
    _rewrite(subj / "ct.nii.gz", fn, dtype=dtype)
    with pytest.raises(PatientError, match=match):
        load_totalsegmentator(subj, spacing=None)


@pytest.mark.parametrize(
    ("fn", "match"),
    [
        (lambda lab: lab + 0.5, "integer class ids"),
        (lambda lab: np.where(lab == 28, np.nan, lab), "integer class ids"),
        (lambda lab: np.where(lab == 28, -3, lab), r"label ids \[-3\]"),
    ],
)
def test_combined_map_values_are_checked(subj, fn, match):
    ref = load_totalsegmentator(subj, spacing=None).labels.numpy()
    shutil.rmtree(subj / "segmentations")
    _, aff = _img(subj / "ct.nii.gz")
    lab = ref.astype(np.float32)
    nib.save(nib.Nifti1Image(lab, aff), subj / "combined_label_map.nii.gz")
    assert load_totalsegmentator(subj, spacing=None).has("L4")  # float but integral: fine
    nib.save(nib.Nifti1Image(fn(lab).astype(np.float32), aff), subj / "combined_label_map.nii.gz")
    with pytest.raises(PatientError, match=match):
        load_totalsegmentator(subj, spacing=None)


def test_other_malformed_inputs(subj):
    (subj / "sonogym.json").write_text("{not json")
    with pytest.raises(PatientError, match="sonogym.json is not a sonogym.json"):
        load_totalsegmentator(subj, spacing=None)
    (subj / "sonogym.json").unlink()
    data, aff = _img(subj / "segmentations" / "vertebrae_L4.nii.gz")
    nib.save(nib.Nifti1Image(data, aff), subj / "segmentations" / "vertebrae_L4.nii")
    with pytest.raises(
        PatientError, match=r"both .*vertebrae_L4.nii.* and .*vertebrae_L4.nii.* exist"
    ):
        load_totalsegmentator(subj, spacing=None)
    (subj / "segmentations" / "vertebrae_L4.nii").unlink()
    with pytest.raises(PatientError, match="must be a lumbar vertebra"):
        load_totalsegmentator(subj, target="T4")
    with pytest.raises(PatientError, match="mask_threshold"):
        load_totalsegmentator(subj, mask_threshold=-1)
    (subj / "segmentations" / "liver.nii.gz").write_bytes(b"\x1f\x8b garbage")
    with pytest.raises(PatientError, match="cannot read mask .*liver.nii.gz"):
        load_totalsegmentator(subj, spacing=None)


def test_inf_is_refused_by_the_volume_itself(subj):
    p = load_totalsegmentator(subj, spacing=None)
    ct = p.ct.clone()
    ct[0, 0, 0] = float("inf")
    with pytest.raises(PatientError, match="NaN or inf"):
        Patient(ct=ct, labels=p.labels, affine=p.affine, name="x")


@pytest.mark.parametrize("bad", [float("nan"), float("-inf")])
def test_a_non_finite_voxel_in_any_slab_is_refused(monkeypatch, bad):
    """The volume checks its CT a slab of x planes at a time: the last slab counts too."""
    from sonogym.anatomy import volume

    monkeypatch.setattr(volume, "_FINITE_CHUNK", 8)  # (5, 2, 3): one x plane per slab
    ct, labels = torch.zeros(5, 2, 3), torch.zeros(5, 2, 3, dtype=torch.uint8)
    Patient(ct=ct, labels=labels, affine=np.eye(4), name="x")
    for where in ((0, 0, 0), (2, 1, 1), (4, 1, 2)):
        bad_ct = ct.clone()
        bad_ct[where] = bad
        with pytest.raises(PatientError, match="NaN or inf"):
            Patient(ct=bad_ct, labels=labels, affine=np.eye(4), name="x")


def test_speckle_seed_follows_content_not_name(subj, tmp_path):
    a = load_totalsegmentator(subj, spacing=None)
    renamed = Path(shutil.copytree(subj, tmp_path / "other-name"))
    assert (
        load_totalsegmentator(renamed, spacing=None).meta["speckle_seed"] == a.meta["speckle_seed"]
    )
    _rewrite(renamed / "ct.nii.gz", lambda ct: np.where(ct == ct.max(), ct - 1, ct))
    assert (
        load_totalsegmentator(renamed, spacing=None).meta["speckle_seed"] != a.meta["speckle_seed"]
    )
    assert speckle_seed(a) == a.meta["speckle_seed"]


@pytest.mark.skipif(sys.platform != "linux", reason="needs a byte-string file system")
def test_non_utf8_folder_name(subj, tmp_path):
    raw = os.path.join(os.fsencode(tmp_path), b"subj-\xff\xfe")
    shutil.copytree(subj, os.fsdecode(raw))
    p = load_totalsegmentator(os.fsdecode(raw), spacing=None)
    assert p.name == "subj-\udcff\udcfe"
    nameless = Patient(ct=p.ct, labels=p.labels, affine=p.affine, name=p.name)  # no meta seed
    assert speckle_seed(nameless) == speckle_seed(
        Patient(ct=p.ct, labels=p.labels, affine=p.affine, name=p.name)
    )


def _body_only(m):
    """The front half of a vertebra mask (RAS array): its body without the posterior arch."""
    ys = np.flatnonzero(m.any((0, 2)))
    out = m.copy()
    out[:, : (ys[0] + ys[-1]) // 2 + 1] = 0
    return out


def test_env_patients_name_the_folder(subj):
    # L4 present and adult-sized but its body alone (no canal, no arch): no frame can be placed.
    f = subj / "segmentations" / "vertebrae_L4.nii.gz"
    _rewrite(f, _body_only)
    with pytest.raises(LandmarkError, match=rf"patient folder {subj}.*L4.*posterior arch"):
        resolve_patients([subj], 0.003)
    with pytest.raises(FileNotFoundError, match=str(subj / "nope")):
        resolve_patients([subj / "nope"], 0.003)
