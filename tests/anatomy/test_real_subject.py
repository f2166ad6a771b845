"""The shared real TotalSegmentator subject (3 mm CT, v1 mask names): loads at 1 mm and at its
native 3 mm, has skin, sane vertebra frames and usable (or clearly refused) pedicle corridors."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import ndimage

from sonogym.anatomy import LandmarkError, load_totalsegmentator
from sonogym.anatomy import labels as L
from sonogym.anatomy import landmarks as LM

SUBJECT = Path(__file__).resolve().parents[1] / "data" / "totalsegmentator_example"
LEVELS = ("L1", "L2", "L3", "L4", "L5")


@pytest.fixture(scope="module")
def real_1mm():
    return load_totalsegmentator(SUBJECT, spacing=0.001, target="L4")


@pytest.fixture(scope="module")
def real_native():
    return load_totalsegmentator(SUBJECT, spacing=None, target="L4")


def _label_at(p, pts):
    ijk = np.rint(p.world_to_voxel_np(pts)).astype(int)
    return p.labels.numpy()[ijk[..., 0], ijk[..., 1], ijk[..., 2]]


def _closed_mask(p, vid):
    """The label ``vid``'s mask with one-voxel pits and holes closed (full volume, bool)."""
    m = p.labels.numpy() == vid
    idx = np.argwhere(m)
    box = tuple(slice(max(a - 3, 0), b + 4) for a, b in zip(idx.min(0), idx.max(0), strict=True))
    out = np.zeros_like(m)
    out[box] = ndimage.binary_fill_holes(ndimage.binary_closing(m[box]) | m[box])
    return out


def test_loads_at_1mm_and_natively(real_1mm, real_native):
    assert np.allclose(real_1mm.spacing, 0.001) and np.allclose(real_native.spacing, 0.003)
    assert real_native.shape == (122, 101, 112)
    # same field of view: 121 intervals of 3 mm = 363 intervals of 1 mm
    assert real_1mm.shape == (364, 301, 334)
    assert np.allclose(real_1mm.bounds, real_native.bounds, atol=1e-6)
    assert "face" in real_1mm.meta["ignored_masks"]  # a v1-only name is listed, not guessed
    for lv in LEVELS:
        assert real_1mm.has(lv)


@pytest.mark.parametrize("which", ["real_1mm", "real_native"])
def test_skin_is_derived_on_the_grid_used(which, request):
    p = request.getfixturevalue(which)
    lab = p.labels.numpy()
    h = p.spacing[0]
    n_skin = int((lab == L.SKIN).sum())
    assert n_skin > 20_000
    # Over the spine at L4 the columns from the back read skin, then the subcutaneous layers:
    # 2 mm (or one 3 mm voxel) where the back faces the column, at most one voxel more where
    # the back slopes (a voxel counts when within 2 mm of the surface along its normal).
    f = p.landmarks.vertebra("L4")
    i, k = np.rint(p.world_to_voxel_np([f.centre[0], 0, f.centre[2]])[[0, 2]]).astype(int)
    n_top = []
    for di in range(-3, 4):
        for dk in range(-3, 4):
            col = lab[i + di, :, k + dk]
            first = int(np.argmax(col > 0))
            n_top.append(int(np.argmax(col[first:] != L.SKIN)))
    assert min(n_top) * h == pytest.approx(max(0.002, h), abs=1e-9)
    assert max(n_top) * h <= max(0.002, h) + h + 1e-9


def test_skin_height_map_follows_the_back(real_1mm):
    p = real_1mm
    f = p.landmarks.vertebra("L4")
    xs = np.linspace(f.centre[0] - 0.04, f.centre[0] + 0.04, 81)
    zs = np.full_like(xs, f.centre[2])
    hgt = p.skin.height(torch.tensor(xs), torch.tensor(zs)).numpy()
    assert np.isfinite(hgt).all()
    assert np.abs(np.diff(hgt)).max() < 0.002  # 1 mm apart: no jumps
    ct = p.ct.numpy()

    def ct_at(y):
        ijk = np.rint(p.world_to_voxel_np(np.stack([xs, y, zs], -1))).astype(int)
        return ct[ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    assert ct_at(hgt - 0.002).max() < -500  # air just outside
    assert ct_at(hgt + 0.004).min() > -300  # tissue just inside
    # the back's skin lies 25-60 mm behind the L4 posterior elements
    idx = np.argwhere(p.labels.numpy() == L.VERTEBRA_IDS["L4"])
    y_bone = p.origin[1] + idx[:, 1].min() * p.spacing[1]
    mid = p.skin.height(torch.tensor(f.centre[0]), torch.tensor(f.centre[2])).item()
    assert 0.025 <= y_bone - mid <= 0.060


def test_vertebra_frames_are_ordered_and_right_handed(real_1mm):
    lm = real_1mm.landmarks
    frames = [lm.vertebra(lv) for lv in LEVELS]
    for up, lo in zip(frames[:-1], frames[1:], strict=True):
        gap = (up.centre - lo.centre) @ up.superior
        assert 0.025 <= gap <= 0.045  # one vertebra + disc
    for f in frames:
        assert f.superior[2] > 0.8 and f.anterior[1] > 0.8 and f.lateral[0] > 0.8
        assert np.allclose(f.rotation.T @ f.rotation, np.eye(3), atol=1e-9)
        assert np.linalg.det(f.rotation) > 0
        assert 0.006 <= f.canal_half_width <= 0.016


@pytest.mark.parametrize("which", ["real_1mm", "real_native"])
def test_every_lumbar_corridor_is_usable_or_refused_by_name(which, request):
    p = request.getfixturevalue(which)
    lm = p.landmarks
    for lv in LEVELS:
        for side in ("left", "right"):
            try:
                t = lm.trajectory(lv, side)
            except LandmarkError as e:
                assert f"{lv} {side}" in str(e) and p.name in str(e)
                assert lv != "L4"  # the task vertebra is never refused on this subject
                continue
            assert t.radius >= LM.MIN_RADIUS
    for side in ("left", "right"):
        assert lm.trajectory("L4", side).radius >= 0.002


def test_real_trajectories_follow_the_rules(real_1mm):
    p = real_1mm
    lm = p.landmarks
    for lv in LEVELS:
        f = lm.vertebra(lv)
        vid = L.VERTEBRA_IDS[lv]
        for side, sgn in (("left", -1), ("right", 1)):
            t = lm.trajectory(lv, side)
            assert t.radius >= 0.0025, (lv, side)  # every corridor is wide on this subject
            s = np.linspace(0, 1, 200)[:, None]
            assert (_label_at(p, t.entry + s * (t.target - t.entry)) == vid).all(), (lv, side)
            assert _label_at(p, t.entry - 2 * p.spacing[0] * t.direction) != vid
            assert (t.entry - f.canal_centre) @ f.anterior < 0
            assert (t.target - f.canal_centre) @ f.anterior > f.canal_half_depth
            assert LM.LENGTH_RANGE[0] <= t.length <= LM.LENGTH_RANGE[1]
            medial = math.degrees(
                math.atan2(-sgn * t.direction @ f.lateral, t.direction @ f.anterior)
            )
            assert medial - 5 * int(lv[1]) == pytest.approx(t.medial_deviation, abs=1e-6)
            lo, hi = LM.MEDIAL_TOLERANCE
            assert lo - 1e-6 <= t.medial_deviation <= hi + 1e-6
            assert abs(t.sagittal_angle) <= LM.SAGITTAL_TOLERANCE + 1e-6
            # the corridor of the planned radius stays in this vertebra from 5 mm past entry (its
            # mask with one-voxel pits and holes closed: mask noise, not missing bone)
            closed = _closed_mask(p, vid)
            e1 = np.cross(t.direction, f.superior)
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(t.direction, e1)
            ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)[:, None]
            for u in np.linspace(0.005, t.length, 30):
                ring = t.entry + u * t.direction + t.radius * (np.cos(ang) * e1 + np.sin(ang) * e2)
                ijk = np.rint(p.world_to_voxel_np(ring)).astype(int)
                assert closed[ijk[:, 0], ijk[:, 1], ijk[:, 2]].all(), (lv, side, u)


def test_speckle_seed_comes_from_the_content(real_1mm, real_native):
    seed = real_1mm.meta["speckle_seed"]
    assert isinstance(seed, int) and 0 <= seed < 2**31
    assert real_native.meta["speckle_seed"] == seed  # the files' content, whatever the spacing
