"""Soft tissue compressed under the probe (``sonogym.ultrasound.compression``): the stress
under a footprint against Newmark's published factors, the exact inverse warp, a layered slab
under uniform pressure against its analytic compression, bone held fixed, CT, labels and the
ultrasound image warped together, and a zero force that samples the static images bit for bit."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from us_synthetic import (
    BONE,
    FAT,
    HU,
    MUSCLE,
    SOFT,
    block_patient,
    layered_patient,
    random_poses,
    straight_down,
)

from sonogym.anatomy.labels import BONE_IDS
from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer
from sonogym.ultrasound._workspace import Workspace
from sonogym.ultrasound.compression import (
    MAX_STRAIN,
    YOUNG_MODULUS,
    TissueCompression,
    corner_influence,
    rectangle_influence,
    warp_shift,
)

#: a footprint so wide that the pressure under it is uniform down to any depth imaged (the
#: analytic slab): 10 m x 10 m
WIDE = (10.0, 10.0)
COLUMN = ProbeGeometry(depth_px=200, width_px=8, depth_spacing=0.5e-3, width_spacing=0.5e-3)
LAYERS = [(0.02, FAT), (0.03, MUSCLE), (0.01, BONE), (0.039, SOFT)]  # 20, 30, 10 mm, then soft


def _force(pressure: float, footprint=WIDE) -> torch.Tensor:
    return torch.tensor([pressure * footprint[0] * footprint[1]])


def _crossings(profile: torch.Tensor, level: float, spacing: float) -> list[float]:
    """Depths (m) where a CT profile crosses ``level``, linearly interpolated."""
    p = profile.double()
    out: list[float] = []
    for k in torch.nonzero((p[:-1] - level) * (p[1:] - level) <= 0).flatten().tolist():
        a, b = p[k].item(), p[k + 1].item()
        at = (k + (level - a) / (b - a)) * spacing if a != b else None
        if at is not None and not (out and abs(out[-1] - at) < 1e-9):  # a sample on the level
            out.append(at)
    return out


@pytest.fixture(scope="module")
def slab():
    return layered_patient(LAYERS, spacing=1e-3, size_xz=(0.06, 0.06))


def test_influence_matches_newmarks_factors_and_decays_beyond_the_footprint():
    one = torch.tensor(1.0, dtype=torch.float64)
    # corner of an m x n rectangle, m = n = 0.5, 1, 2 (Newmark's chart: 0.0840, 0.1752, 0.2325)
    for m, want in ((0.5, 0.0840), (1.0, 0.1752), (2.0, 0.2325)):
        assert float(corner_influence(m * one, m * one, one)) == pytest.approx(want, rel=2e-3)
    z = torch.tensor([1e-5, 0.01, 0.02, 0.04, 0.08], dtype=torch.float64)
    centre = rectangle_influence(0 * one, 0 * one, z, 0.0375, 0.005)
    assert float(centre[0]) == pytest.approx(1.0, abs=1e-3)  # the pressure itself at the face
    assert bool((centre[1:] < centre[:-1]).all())  # the load spreads with depth
    # at the footprint's elevation edge (5 mm) just under the face, half the pressure (the
    # edge of a uniform load); beyond it, at 5 mm depth, less and less
    edge = rectangle_influence(0 * one, 0.005 * one, 1e-5 * one, 0.0375, 0.005)
    assert float(edge) == pytest.approx(0.5, abs=0.01)
    y = torch.tensor([0.0, 0.005, 0.01, 0.02], dtype=torch.float64)
    across = rectangle_influence(0 * y, y, 0.005 + 0 * y, 0.0375, 0.005)
    assert bool((across[1:] < across[:-1]).all()) and float(across[-1]) < 0.05


def test_warp_shift_solves_s_minus_c_of_s_exactly():
    g = torch.Generator().manual_seed(0)
    eps = torch.rand(40, 60, generator=g) * MAX_STRAIN
    free = (torch.rand(40, 60, generator=g) > 0.03).float()
    shift, total = warp_shift(eps, free)
    for r in range(40):
        e = eps[r].double().numpy().copy()
        stop = np.flatnonzero(free[r].numpy() == 0)
        if len(stop):
            e[stop[0] :] = 0.0  # the support and everything behind it do not compress
        bounds = np.arange(61) - 0.5
        c = np.concatenate([[0.0], np.cumsum(e)])  # compression at the cells' bounds
        assert float(total[r]) == pytest.approx(c[-1], abs=1e-4)
        for j in range(60):
            s = np.interp(j, bounds - c, bounds) if j <= (bounds - c)[-1] else j + c[-1]
            assert float(shift[r, j]) == pytest.approx(s - j, abs=2e-4)


def test_a_layered_slab_compresses_each_layer_by_thickness_times_pressure_over_e(slab):
    """Uniform pressure p on fat (20 mm) and muscle (30 mm) resting on bone: each layer
    shortens by t p / E while the strain is small (here 1-2 %), and by the model's saturating
    law t eps_max (1 - exp(-p / (E eps_max))) at any pressure; the bone and what lies behind it
    keep their thickness (rigid, fixed). Layer bounds are read from the CT (sub-pixel)."""
    sl = Slicer(slab, COLUMN, upsample=False)
    model = TissueCompression(COLUMN, sl.block, footprint=WIDE, stride=(1, 1))
    pos, rot = straight_down(1)

    def bounds(pressure: float) -> np.ndarray:
        warp = model.bind(_force(pressure))
        ct = sl(pos, rot, warp=warp).ct[0, 0, :, 4]
        sp = COLUMN.depth_spacing
        fat_muscle = _crossings(ct, (HU[FAT] + HU[MUSCLE]) / 2, sp)[0]
        muscle_bone, bone_soft = _crossings(ct, (HU[MUSCLE] + HU[BONE]) / 2, sp)[:2]
        soft_air = _crossings(ct, (HU[SOFT] - 1000) / 2, sp)[-1]  # the slab's far side
        return np.array([fat_muscle, muscle_bone, bone_soft, soft_air])

    rest = bounds(0.0)
    e_fat, e_muscle = YOUNG_MODULUS["fat"], YOUNG_MODULUS["muscle"]
    for pressure, law in ((400.0, "linear"), (4000.0, "model"), (30000.0, "model")):
        moved = rest - bounds(pressure)  # each bound moved this far toward the probe
        got = np.array([moved[0], moved[1] - moved[0]])  # fat, muscle compression
        thick = np.array([0.02, 0.03])
        e = np.array([e_fat, e_muscle])
        if law == "linear":
            want = thick * pressure / e
        else:
            want = thick * MAX_STRAIN * -np.expm1(-pressure / (e * MAX_STRAIN))
        np.testing.assert_allclose(got, want, rtol=0.05, err_msg=f"{pressure} Pa")
        # bone and the soft tissue behind it move as one block: thicknesses unchanged (to the
        # 0.5 mm samples' reading of a kinked CT ramp: 0.15 mm)
        assert moved[2] == pytest.approx(moved[1], abs=1.5e-4)
        assert moved[3] == pytest.approx(moved[2], abs=1.5e-4)


def test_compression_grows_with_force_and_never_inverts_tissue(slab):
    sl = Slicer(slab, COLUMN)
    model = TissueCompression(COLUMN, sl.block, footprint=(0.004, 0.01))
    pos, rot = straight_down(1)
    totals = []
    for force in (0.0, 0.5, 2.0, 10.0, 20.0, 30.0):
        warp = model.bind(torch.tensor([force]))
        labels = sl(pos, rot, warp=warp).labels[0, 0, :, 4]
        totals.append(float(warp.centre[0]))
        # no layer passes another: the column still reads fat, muscle, bone, soft tissue
        runs = labels[torch.cat([torch.tensor([True]), labels[1:] != labels[:-1]])].tolist()
        assert runs[:4] == [FAT, MUSCLE, BONE, SOFT], runs
    assert totals[0] == 0.0
    assert all(b > a for a, b in zip(totals, totals[1:], strict=False)), totals
    assert totals[-1] < MAX_STRAIN * 0.05  # at most half of the 50 mm above the bone


def test_a_zero_force_samples_the_static_images_bit_for_bit(small_phantom):
    sl = Slicer(small_phantom, ProbeGeometry.linear_2d())
    model = TissueCompression(sl.probe, sl.block)
    c = small_phantom.landmarks.vertebra("L4").centre
    x = torch.tensor([c[0], c[0] + 0.02, c[0] - 0.03], dtype=torch.float64)
    z = torch.tensor([c[2], c[2] - 0.01, c[2] + 0.02], dtype=torch.float64)
    pos, rot = small_phantom.skin.surface_pose(x, z, torch.full_like(x, math.pi))
    plain = sl(pos, rot)
    warp = model.bind(torch.tensor([0.0, 0.0, 0.0]))
    zero = sl(pos, rot, warp=warp)
    assert torch.equal(plain.ct, zero.ct) and torch.equal(plain.labels, zero.labels)
    pressed = sl(pos, rot, warp=model.bind(torch.tensor([0.0, 15.0, 0.0])))
    # each env on its own: the unpressed ones keep their bits beside a pressed one
    assert torch.equal(pressed.ct[[0, 2]], plain.ct[[0, 2]])
    assert not torch.equal(pressed.ct[1], plain.ct[1])


def test_labels_ct_and_ultrasound_move_together_and_bone_comes_closer(small_phantom):
    """At the transverse view over L4 at 0 and 20 N: in every column that meets bone, the
    first bone row of the label image rises by the column's compression, the CT is bone there
    too, and the ultrasound's bone echo (the brightest row near it) rises with it."""
    sl = Slicer(small_phantom, ProbeGeometry.linear_2d())
    model = TissueCompression(sl.probe, sl.block)
    c = small_phantom.landmarks.vertebra("L4").centre
    x, z = small_phantom.skin.aim(torch.tensor(c[None]), torch.tensor([0]))
    pos, rot = small_phantom.skin.surface_pose(x, z, torch.full_like(x, math.pi))
    sim = ModelBasedSimulator("physical")
    bone_lut = torch.zeros(256, dtype=torch.bool)
    bone_lut[sorted(BONE_IDS)] = True

    def look(force: float):
        warp = model.bind(torch.tensor([force]))
        s = sl(pos, rot, warp=warp)
        bone = bone_lut[s.labels[0, 0].long()]  # (H, W)
        first = torch.where(bone.any(0), bone.float().argmax(0), -1)
        img = sim.simulate(s)[0, 0]
        return s, bone, first, img, float(warp.centre[0])

    s0, bone0, first0, img0, _ = look(0.0)
    s1, bone1, first1, img1, centre = look(20.0)
    assert centre > 2e-3  # mm of compression at 20 N
    cols = torch.nonzero((first0 >= 0) & (first1 >= 0)).flatten()
    assert len(cols) > 20
    rise = (first0[cols] - first1[cols]).float() * sl.probe.depth_spacing
    assert float(rise.min()) > 1e-3 and float(rise.max()) < 0.03  # every bone came closer
    # CT and labels sampled at the same (moved) points: bone-labelled pixels read as bone
    assert float(s1.ct[0, 0][bone1].median()) > 300.0
    # the ultrasound's bone echo moved with the labels: brightest row within 3 mm of the
    # labels' first bone row, at both forces
    for img, first in ((img0, first0), (img1, first1)):
        near = []
        for col in cols.tolist():
            top = max(0, int(first[col]) - 6)
            near.append(top + int(img[top : int(first[col]) + 6, col].argmax()) - int(first[col]))
        assert float(np.median(np.abs(near))) <= 3, near


def test_the_volume_probes_outer_slices_compress_less(slab):
    """Beyond the footprint's edges the stress, and so the compression, falls off: the 3-D
    probe's face spans its slices (-20 ... +20 mm), so its outer slices, at the face's edges,
    are pressed less than its centre slice."""
    probe = ProbeGeometry.volume_3d()
    sl = Slicer(slab, probe)
    assert sl.block == (1, 1)  # 2 mm pixels: one sample each
    model = TissueCompression(probe, sl.block)
    pos, rot = straight_down(1)
    labels = sl(pos, rot).labels.transpose(-1, -2).contiguous()  # (1, E, W, H): depth last
    shift = model.bind(torch.tensor([20.0]))(labels, slice(0, 1), Workspace("cpu"))
    total = shift[0, :, probe.width_px // 2, -1]  # rows below the bone: the whole compression
    assert float(total[2]) > 1.0  # rows of 2 mm
    assert total[2] > total[1] > total[0] > 0 and total[2] > total[3] > total[4] > 0, total
    assert float(total[0]) == pytest.approx(float(total[4]))  # symmetric


def test_the_warp_on_beams_2_mm_apart_agrees_with_the_warp_at_every_sample():
    """The envs compute the compression on beams about 2 mm apart (``WARP_GRID``) and
    interpolate it across: against the warp at every 1 mm sample, over a bone block of limited
    width (columns with and without bone side by side), the labels differ in < 0.5 % of
    pixels, the bone surface not at all, the compression under the centre by < 2 %."""
    patient = block_patient(ct_noise=0.0)
    sl = Slicer(patient, ProbeGeometry.linear_2d())
    pos, rot = straight_down(3, x=torch.tensor([0.0, 0.012, -0.018]))  # the block: |x| < 20 mm
    fine = TissueCompression(sl.probe, sl.block, stride=(1, 1))
    grid = TissueCompression(sl.probe, sl.block)
    assert sl.block == (2, 2) and grid.stride == (1, 2)
    for force in (5.0, 20.0):
        f = torch.full((3,), force)
        wa, wb = fine.bind(f), grid.bind(f)
        a, b = sl(pos, rot, warp=wa), sl(pos, rot, warp=wb)
        assert float((a.labels != b.labels).float().mean()) < 0.005
        bone_a, bone_b = a.labels[:, 0] == BONE, b.labels[:, 0] == BONE
        assert torch.equal(bone_a.float().argmax(1), bone_b.float().argmax(1))
        torch.testing.assert_close(wb.centre, wa.centre, rtol=0.02, atol=0.0)


def test_pressed_images_have_the_same_bits_alone_in_a_batch_and_on_two_threads():
    patient = block_patient()
    sl = Slicer(patient, ProbeGeometry.linear_2d(), chunk_samples=4000)  # several chunks
    model = TissueCompression(sl.probe, sl.block)
    pos, rot = random_poses(9, seed=3, max_angle=0.3)
    force = torch.linspace(0.0, 30.0, 9)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = sl(pos, rot, warp=model.bind(force))
        torch.set_num_threads(2)
        two = sl(pos, rot, warp=model.bind(force))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one.ct, two.ct) and torch.equal(one.labels, two.labels)
    alone = sl(pos[4:5], rot[4:5], warp=model.bind(force[4:5]))
    assert torch.equal(alone.ct[0], one.ct[4]) and torch.equal(alone.labels[0], one.labels[4])
