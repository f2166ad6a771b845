"""Landmarks on rough, resampled and damaged vertebra masks of the real subject.

The shared subject (3 mm, TotalSegmentator model output) is cropped to L1-S1 and degraded the
ways real masks differ: other voxel sizes (masks resampled nearest, or smoothed and thresholded
as model output looks), one voxel more or less bone, gaps cut through the laminae, thin bridges
opened, holes and pits, a canal label, a posterior arch missing, a field of view that cuts a
vertebra. Every whole vertebra keeps a frame within 2 mm and 5 deg of the undegraded one, and a
corridor on each side unless the damage removed the bone the corridor needs (module
docstring of ``sonogym.anatomy.landmarks``)."""

import numpy as np
import pytest
from scipy import ndimage
from spine_masks import LEVELS, VIDS, per_vertebra, resample, spine_crop
from spine_masks import axis_errors as _axis_errors
from spine_masks import landmarks_of as _landmarks

from sonogym.anatomy import LandmarkError
from sonogym.anatomy import labels as L
from sonogym.anatomy import landmarks as LM

CENTRE_TOL = 0.002  # m
AXIS_TOL = 5.0  # deg


@pytest.fixture(scope="module")
def spine(tmp_path_factory):
    """(labels, affine): the subject's spine masks at 3 mm, cropped to L1-S1 (+4 voxels)."""
    return spine_crop(tmp_path_factory.mktemp("spine") / "subj")


@pytest.fixture(scope="module")
def reference(spine):
    return _landmarks(*spine, "undegraded")


# ----------------------------------------------------------------------------- degradations


def posterior(lab, aff, ref, behind=0.0):
    """Voxels of L1-L5 more than ``behind`` (m) behind their canal centre (reference frames)."""
    h, out = aff[0, 0], np.zeros(lab.shape, bool)
    for lv in LEVELS:
        f = ref.vertebrae[lv]
        idx = np.argwhere(lab == L.VERTEBRA_IDS[lv])
        q = (aff[:3, 3] + idx * h - f.canal_centre) @ f.rotation
        out[tuple(idx[q[:, 1] < -behind].T)] = True
    return out


def slits(lab, aff, ref, at=(-0.006, 0.0, 0.006), width=1):
    """Gaps ``width`` voxels wide, the vertebra's full height, through the posterior arch at
    lateral offsets ``at`` (m; 0 is the spinous process's base, +-6 mm the laminae)."""
    h, out = aff[0, 0], lab.copy()
    for lv in LEVELS:
        f = ref.vertebrae[lv]
        idx = np.argwhere(lab == L.VERTEBRA_IDS[lv])
        q = (aff[:3, 3] + idx * h - f.canal_centre) @ f.rotation
        back = q[:, 1] < -0.3 * f.canal_half_depth
        for x in at:
            out[tuple(idx[back & (np.abs(q[:, 0] - x) < width * h / 2 + 1e-9)].T)] = 0
    return out


def holes(lab, fraction, surface, seed=0):
    """Vertebra voxels removed at random: inside the bone, or on its surface (pits)."""
    m = np.isin(lab, VIDS)
    inner = ndimage.binary_erosion(m)
    pick = (m & ~inner) if surface else inner
    out = lab.copy()
    out[pick & (np.random.default_rng(seed).random(lab.shape) < fraction)] = 0
    return out


def _variant(name, lab, aff, ref):
    """(labels, affine, depth of bone removed from every surface, m) of a named variant."""
    h = aff[0, 0]
    cube = ndimage.generate_binary_structure(3, 3)
    ball2 = ndimage.iterate_structure(ndimage.generate_binary_structure(3, 1), 2)
    if name.startswith(("0.8", "1.5", "2.0")):
        size, _, rest = name.partition(" ")
        lab, aff = resample(lab, aff, float(size) * 1e-3, smooth=rest.startswith("smooth"))
        h, rest = aff[0, 0], rest.removeprefix("smooth").strip()
    else:
        rest = name.removeprefix("3.0").strip()
    removed = 0.0
    if rest == "eroded":
        lab, removed = per_vertebra(lab, ndimage.binary_erosion), h
    elif rest == "dilated":
        lab = per_vertebra(lab, ndimage.binary_dilation)
    elif rest == "arch eroded":  # the posterior arch one voxel thinner: its thin parts break
        lab = per_vertebra(lab, ndimage.binary_erosion, posterior(lab, aff, ref, 0.003))
    elif rest == "opened":  # bridges thinner than 2 voxels (4 at 1.5 mm) removed
        lab = per_vertebra(lab, lambda m: ndimage.binary_opening(m, ball2 if h < 0.002 else cube))
    elif rest == "slits":
        lab = slits(lab, aff, ref, width=max(1, round(0.003 / h)))  # 3 mm gaps
    elif rest == "holes":
        lab = holes(lab, 0.01, surface=False)
    elif rest == "pits":
        lab = holes(lab, 0.2, surface=True)
    else:
        assert rest == "", name
    return lab, aff, removed


VARIANTS = [
    "1.5",
    "1.5 smooth",
    "2.0",
    "2.0 smooth",
    "0.8 smooth",
    "1.5 eroded",
    "1.5 dilated",
    "3.0 eroded",
    "3.0 dilated",
    "1.5 arch eroded",
    "1.5 opened",
    "1.5 slits",
    "3.0 slits",
    "1.5 smooth holes",
    "3.0 pits",
]


@pytest.mark.parametrize("name", VARIANTS)
def test_every_level_keeps_its_frame_and_corridors(name, spine, reference):
    lab, aff, removed = _variant(name, *spine, reference)
    lm = _landmarks(lab, aff, name)
    for lv in LEVELS:
        f, ref = lm.vertebra(lv), reference.vertebrae[lv]
        assert np.linalg.norm(f.centre - ref.centre) < CENTRE_TOL, lv
        assert max(_axis_errors(f, ref)) < AXIS_TOL, lv
        for side in ("left", "right"):
            if (lv, side) in lm.trajectories:
                assert lm.trajectory(lv, side).radius >= LM.MIN_RADIUS
                continue
            # Refused only where the damage took the bone the undegraded corridor needs.
            why = lm.refused[(lv, side)]
            assert why.startswith(f"{lv} {side}:"), why
            ref_radius = reference.trajectories[(lv, side)].radius
            assert ref_radius - removed < LM.MIN_RADIUS, (lv, side, why)


def test_opened_3mm_arch_still_gives_frames(spine, reference):
    # An opening by a 3-voxel cube at 3 mm removes all bone thinner than 9 mm: the laminae go,
    # the arch is open wider than the closings bridge, and its convex hull gives the canal.
    lab, aff = spine
    opened = per_vertebra(lab, lambda m: ndimage.binary_opening(m, np.ones((3, 3, 3), bool)))
    lm = _landmarks(opened, aff, "opened")
    for lv in LEVELS:
        f, ref = lm.vertebra(lv), reference.vertebrae[lv]
        assert np.linalg.norm(f.centre - ref.centre) < CENTRE_TOL, lv
        assert max(_axis_errors(f, ref)) < AXIS_TOL, lv
        for side in ("left", "right"):  # planned, or refused by name
            assert (lv, side) in lm.trajectories or lm.refused[(lv, side)].startswith(lv)


def test_arch_open_behind_the_canal_gives_the_canal_from_its_hull(spine, reference):
    lab, aff = spine
    open_ = lab.copy()  # L3 cut 4 mm behind its canal centre: laminae and spinous process gone
    open_[posterior(lab, aff, reference, behind=0.004) & (lab == L.VERTEBRA_IDS["L3"])] = 0
    f, ref = _landmarks(open_, aff, "open").vertebra("L3"), reference.vertebrae["L3"]
    assert np.linalg.norm(f.centre - ref.centre) < CENTRE_TOL
    assert max(_axis_errors(f, ref)) < AXIS_TOL


def test_canal_label_stands_in_for_a_missing_arch(spine, reference):
    lab, aff = spine
    h, f3 = aff[0, 0], reference.vertebrae["L3"]
    bare = lab.copy()  # L3's body alone: pedicles and arch gone
    bare[posterior(lab, aff, reference, behind=-0.011) & (lab == L.VERTEBRA_IDS["L3"])] = 0
    lm = _landmarks(bare, aff, "bare")
    with pytest.raises(
        LandmarkError, match=r"bare: vertebra L3: .*no vertebral ring.*spinal_canal"
    ):
        lm.vertebra("L3")
    assert set(lm.vertebrae) == {"L1", "L2", "L4", "L5"}
    # A spinal_canal label (a 12 mm tube) around the undegraded canal centre gives it back.
    ijk = np.argwhere(bare == 0)
    q = (aff[:3, 3] + ijk * h - f3.canal_centre) @ f3.rotation
    tube = ijk[(np.hypot(q[:, 0], q[:, 1]) < 0.006) & (np.abs(q[:, 2]) < 0.012)]
    bare[tuple(tube.T)] = L.SPINAL_CANAL
    f = _landmarks(bare, aff, "with canal").vertebra("L3")
    assert np.linalg.norm(f.canal_centre - f3.canal_centre) < CENTRE_TOL
    assert np.linalg.norm(f.centre - f3.centre) < CENTRE_TOL
    assert max(_axis_errors(f, f3)) < AXIS_TOL


def test_a_canal_label_does_not_move_a_found_ring(spine, reference):
    lab, aff = spine
    lab = lab.copy()
    lab[lab == 0] = L.SPINAL_CANAL  # a canal label everywhere outside the bone: not used
    lm = _landmarks(lab, aff, "canal label")
    for lv in LEVELS:
        assert np.array_equal(lm.vertebra(lv).rotation, reference.vertebrae[lv].rotation)


def test_vertebra_cut_by_the_field_of_view_is_refused_by_name(spine, reference):
    lab, aff = spine
    h = aff[0, 0]
    top = int(np.argwhere(lab == L.VERTEBRA_IDS["L1"])[:, 2].mean())  # through L1's middle
    lm = _landmarks(np.ascontiguousarray(lab[:, :, :top]), aff, "cut")
    with pytest.raises(LandmarkError, match=r"cut: vertebra L1: .*field of view's edge \(last z"):
        lm.vertebra("L1")
    assert ("L1", "left") not in lm.trajectories
    for lv in LEVELS[1:]:
        f, ref = lm.vertebra(lv), reference.vertebrae[lv]
        assert np.linalg.norm(f.centre - ref.centre) < CENTRE_TOL
        assert max(_axis_errors(f, ref)) < AXIS_TOL
        assert (lv, "left") in lm.trajectories and (lv, "right") in lm.trajectories
    assert h == pytest.approx(0.003)
