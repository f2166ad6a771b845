"""The phantom's spine has the shapes ultrasound sees: one continuous arch from the spinous tip
over the laminae to the facets, facet joints between levels, an interlaminar window bridged by
the ligamentum flavum, a median sacral crest, and iliac crests rising beside L4-L5."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from sonogym.anatomy import PhantomParams, make_phantom
from sonogym.anatomy import labels as L
from sonogym.anatomy.morphometry import PROFILE_DEPTH, bone_hit_depths, measure, muscle_profile

SMALL = PhantomParams(spacing=0.002)
SEEDS = (0, 3, 7)


@pytest.fixture(scope="module")
def phantoms(small_phantom):
    return [small_phantom] + [make_phantom(s, SMALL) for s in SEEDS[1:]]


def _frame_coords(f, pts):
    return (np.asarray(pts) - f.centre) @ f.rotation * 1e3


def _goal_view_gap(p):
    """(longest gap in mm, label of the shallowest bone) across the transverse L4 goal view
    (the probe on the skin above the L4 body centroid, beam along the skin normal). A gap is a
    run of beams between the facets (within 6 mm of the canal's side walls, at the canal's
    depth) whose first bone hit is missing or not behind the canal centre: the beam slipped
    through the arch."""
    f = p.landmarks.vertebra("L4")
    x, z = float(f.centre[0]), float(f.centre[2])
    step = 0.5
    u = np.arange(-37.0, 37.0 + 1e-9, step)
    d = bone_hit_depths(p, x, z, math.pi, u)
    pos, rot = p.skin.surface_pose(
        torch.tensor([x], dtype=torch.float64),
        torch.tensor([z], dtype=torch.float64),
        torch.tensor([math.pi], dtype=torch.float64),
    )
    pos, rot = pos[0].numpy(), rot[0].numpy()
    beams = pos + (u[:, None] * 1e-3) * rot[:, 0]
    cc = _frame_coords(f, f.canal_centre)
    at_canal = _frame_coords(f, beams + ((f.canal_centre - pos) @ rot[:, 2]) * rot[:, 2])
    hits = beams + (d[:, None] * 1e-3) * rot[:, 2]
    window = np.abs(at_canal[:, 0] - cc[0]) <= f.canal_half_width * 1e3 + 6.0
    assert window.sum() * step > 30  # the window spans the arch
    gap = window & ((d >= 100.0) | (_frame_coords(f, hits)[:, 1] >= cc[1]))
    longest = run = 0
    for g in gap:
        run = run + 1 if g else 0
        longest = max(longest, run)
    top = np.argmin(np.where(window, d, np.inf))
    ijk = np.rint(p.world_to_voxel_np(hits[top])).astype(int)
    return longest * step, int(p.labels.numpy()[tuple(ijk)])


def test_the_arch_is_one_continuous_bone_line_in_the_goal_view(phantoms):
    # The transverse goal view sits above the L4 body centroid with the beam along the skin's
    # normal; on a sloping lower back its plane may instead cross the L4-L5 interlaminar
    # window or L5's arch (the real subject's goal view shows L5's spinous process). Where it
    # crosses L4's arch, the spinous process, laminae and articular processes make one bone
    # line from facet to facet: no beam slips through to the canal.
    checked = 0
    for p in phantoms:
        gap, top = _goal_view_gap(p)
        if top == L.VERTEBRA_IDS["L4"]:
            checked += 1
            assert gap <= 2.0, (p.name, gap)
    assert checked >= 2


def test_facet_joints_link_each_level_to_the_next_on_both_sides(phantoms):
    for p in phantoms:
        m = measure(p)
        for lv in ("L1", "L2", "L3", "L4", "L5"):
            # the contact zones with the level below exist on both sides (facet_width is NaN
            # otherwise) and lie beside the canal, 20-50 mm apart
            assert 20.0 <= m.levels[lv]["facet_width"] <= 50.0, (p.name, lv)
        # L4-L5: two facing articular plates, not a point contact: on each side, L4 bone within
        # 4 mm of L5 (behind the canal centre, lateral of the canal's middle) fills > 150 mm^3
        f = p.landmarks.vertebra("L4")
        lab = p.labels.numpy()
        l4 = p.origin + np.argwhere(lab == L.VERTEBRA_IDS["L4"]) * p.spacing
        l5 = p.origin + np.argwhere(lab == L.VERTEBRA_IDS["L5"]) * p.spacing
        dist, _ = cKDTree(l5 * 1e3).query(l4 * 1e3, distance_upper_bound=4.0)
        q = _frame_coords(f, l4)
        cc = _frame_coords(f, f.canal_centre)
        zone = np.isfinite(dist) & (q[:, 1] < cc[1])
        for side in (-1.0, 1.0):
            on_side = zone & (side * (q[:, 0] - cc[0]) > 0.7 * f.canal_half_width * 1e3)
            assert on_side.sum() * (p.spacing[0] * 1e3) ** 3 > 150.0, (p.name, side)


def _paramedian(p, f, label):
    """(N, 3) mm, frame of f: voxels of ``label`` over the canal's lateral half, behind it."""
    q = _frame_coords(f, p.origin + np.argwhere(p.labels.numpy() == label) * p.spacing)
    cc = _frame_coords(f, f.canal_centre)
    lat = np.abs(q[:, 0] - cc[0])
    cw = f.canal_half_width * 1e3
    return q[(lat >= 0.5 * cw) & (lat <= cw) & (q[:, 1] < cc[1])]


def test_the_l4_l5_interlaminar_window_is_open_and_bridged_by_the_flavum(phantoms):
    windows = [measure(p).levels["L4"]["interlaminar_window"] for p in phantoms]
    # Most phantoms show the window (in the shipped population of 40 its 5th percentile is
    # +1.6 mm; one phantom in 40 has its L4 and L5 laminae overlapping, as in hyperlordosis).
    assert sum(w > 0 for w in windows) >= 2, windows
    for p in phantoms:
        f = p.landmarks.vertebra("L4")
        cc = _frame_coords(f, f.canal_centre)
        l4 = _paramedian(p, f, L.VERTEBRA_IDS["L4"])
        l5 = _paramedian(p, f, L.VERTEBRA_IDS["L5"])
        lig = _paramedian(p, f, L.SPINAL_LIGAMENTS)
        # from the lowest point of L4's laminae to the top of L5's, just behind the canal: the
        # ligamentum flavum
        low, high = l5[:, 2].max() - 3.0, l4[:, 2].min() + 3.0
        near = (lig[:, 2] > low) & (lig[:, 2] < high)
        near &= lig[:, 1] > cc[1] - f.canal_half_depth * 1e3 - 8.0
        assert near.sum() * (p.spacing[0] * 1e3) ** 3 > 20.0, p.name  # mm^3


def test_the_sacrum_has_a_median_crest(phantoms):
    for p in phantoms:
        lab = p.labels.numpy()
        idx = np.argwhere(lab == L.LABEL_IDS["sacrum"])
        f = p.landmarks.vertebra("L5")
        q = _frame_coords(f, p.origin + idx * p.spacing)
        # in the upper sacrum, the midline is the most posterior part of the dorsal surface
        upper = q[:, 2] > np.percentile(q[:, 2], 60)
        mid = upper & (np.abs(q[:, 0]) < 3.0)
        para = upper & (np.abs(np.abs(q[:, 0]) - 12.0) < 3.0)
        assert q[mid, 1].min() < q[para, 1].min() - 2.0, p.name


def test_the_iliac_crests_rise_from_beside_the_sacrum_to_beside_l4_l5(phantoms):
    for p in phantoms:
        lab = p.labels.numpy()
        f4, f5 = p.landmarks.vertebra("L4"), p.landmarks.vertebra("L5")
        s4 = _frame_coords(f5, f4.centre)[2]
        for hip in (77, 78):
            q = _frame_coords(f5, p.origin + np.argwhere(lab == hip) * p.spacing)
            summit = q[np.argmax(q[:, 2])]
            psis = q[np.argmin(q[:, 1])]  # the posterior superior iliac spine
            # the summit: beside the spine, between the L5 centre and the L4 centre's top
            assert 0.0 <= summit[2] <= s4 + 10.0, (p.name, hip, summit)
            assert abs(summit[0]) > 60.0
            # the PSIS: medial, behind the sacrum's upper part, well below the summit
            assert 30.0 <= abs(psis[0]) <= 60.0, (p.name, hip, psis)
            assert psis[2] < summit[2] - 20.0


def test_the_paraspinal_muscles_rise_behind_the_tips_with_a_fat_cleft_over_them(phantoms):
    """Transverse L4 goal view: two convex muscle backs meeting in a V over the spinous tip, as
    on real CT (where the beams' first tissue under the fat is muscle beside the tip and bone
    at it)."""
    u = np.arange(-35.0, 35.0 + 1e-9, 1.0)
    for p in phantoms:
        f = p.landmarks.vertebra("L4")
        x, z = float(f.centre[0]), float(f.centre[2])
        bone = bone_hit_depths(p, x, z, math.pi, u)
        muscle = muscle_profile(p, f, u)
        a = b = int(np.argmin(bone))  # a beam on the spinous tip
        assert muscle[a] == PROFILE_DEPTH, p.name  # bone before any muscle
        while a > 0 and muscle[a - 1] == PROFILE_DEPTH:  # the beams that meet no muscle
            a -= 1
        while b < len(u) - 1 and muscle[b + 1] == PROFILE_DEPTH:
            b += 1
        for lobe in (muscle[: max(a - 8, 0)], muscle[b + 9 :]):
            # each lobe's back rises behind the tip ...
            assert lobe.size and lobe.min() < bone[a] - 5.0, (p.name, lobe.min(), bone[a])
        for beside in (muscle[max(a - 2, 0) : a], muscle[b + 1 : b + 3]):
            # ... and the muscle right beside the cleft lies deeper than the lobes' tops (the V)
            assert beside.size and beside.max() > muscle.min() + 5.0, (p.name, beside)
