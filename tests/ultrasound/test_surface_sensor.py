import numpy as np
import pytest
import torch
from us_synthetic import BONE, HU, block_patient, random_poses, straight_down

from sonogym.anatomy.patient import Patient
from sonogym.ultrasound import ProbeGeometry, Slicer
from sonogym.ultrasound.surface_sensor import BoneSurfaceSensor

OTHER_BONE = 27  # L5: a bone that is not the target (BONE = 28 = L4)


@pytest.fixture(scope="module")
def patient():
    # Bone (label 28) for |x| <= 20 mm at 35-47 mm below the skin (y = 0), 1 mm voxels; a plate
    # of another bone for 0 < x <= 10 mm at 25-28 mm shadows part of it.
    p = block_patient(ct_noise=0.0)
    lab = p.labels.numpy().copy()
    xs = p.origin[0] + 1e-3 * np.arange(lab.shape[0])
    ys = p.origin[1] + 1e-3 * np.arange(lab.shape[1])
    bx = (xs > 0) & (xs <= 0.010)
    by = (ys >= 0.025) & (ys < 0.028)
    lab[np.ix_(bx, by, np.ones(lab.shape[2], bool))] = OTHER_BONE
    ct = np.vectorize({**HU, OTHER_BONE: 1400.0}.get)(lab).astype(np.float32)
    return Patient(torch.from_numpy(ct), torch.from_numpy(lab), p.affine, name="block+plate")


@pytest.fixture(scope="module")
def sensor(patient):
    return BoneSurfaceSensor(patient)


def _down(n=1, x=0.0):
    # 0.2 mm above the skin: pixel rows fall between voxel centres, no nearest-label ties
    pos, rot = straight_down(n, x=x, y=-0.0002)
    return pos.float(), rot.float()


def test_first_bone_boundary_per_scan_line_with_occlusion(sensor):
    pos, rot = _down()
    s = sensor.sense(pos, rot, torch.zeros(1, dtype=torch.long), BONE, missing_rate=0.0)
    assert s.points.shape == (1, 50, 3) and s.valid.shape == s.visible.shape == (1, 50)
    x = s.points[0, :, 0].numpy()
    np.testing.assert_allclose(x, (np.arange(50) - 24.5) * 1e-3, atol=1e-9)  # 1 mm columns
    on_bone = np.abs(x) <= 0.020
    shadowed = (x > 0) & (x <= 0.010)
    want = on_bone & ~shadowed
    assert (s.visible[0].numpy() == want).all()
    assert torch.equal(s.valid, s.visible)  # missing_rate 0
    # the surface point is the first bone pixel: within one pixel below the bone's top (35 mm)
    y = s.points[0, s.visible[0], 1].numpy()
    assert ((y >= 0.035 - 1e-3) & (y <= 0.036 + 1e-3)).all()
    np.testing.assert_allclose(s.points[0, :, 2].numpy(), 0.0, atol=1e-9)


def test_points_follow_the_probe_pose(sensor):
    # lateral shift by 7 mm moves the sensed points by 7 mm
    pos0, rot = _down()
    pos1 = pos0.clone()
    pos1[:, 0] -= 0.007
    pid = torch.zeros(1, dtype=torch.long)
    a = sensor.sense(pos0, rot, pid, BONE, missing_rate=0.0)
    b = sensor.sense(pos1, rot, pid, BONE, missing_rate=0.0)
    assert torch.allclose(b.points[0, 10:, 0], a.points[0, 10:, 0] - 0.007, atol=1e-7)
    assert torch.equal(b.visible[0, 7:], a.visible[0, :43])  # column i sees x_i - 7 mm


def test_target_per_env_and_other_bones_are_not_the_target(sensor):
    pos, rot = _down(2)
    s = sensor.sense(pos, rot, torch.zeros(2, dtype=torch.long), torch.tensor([BONE, OTHER_BONE]))
    x = s.points[1, :, 0].numpy()
    assert (s.visible[1].numpy() == ((x > 0) & (x <= 0.010))).all()  # the plate is seen
    assert s.visible[0].sum() > 20


def test_missing_rate_is_the_drop_probability(sensor):
    pos, rot = _down(64, x=torch.linspace(-0.01, 0.01, 64, dtype=torch.float64))
    pid = torch.zeros(64, dtype=torch.long)
    g = torch.Generator().manual_seed(0)
    vis = kept = 0
    for _ in range(10):
        s = sensor.sense(pos, rot, pid, BONE, g, missing_rate=0.2)
        assert not (s.valid & ~s.visible).any()
        vis += int(s.visible.sum())
        kept += int(s.valid.sum())
    assert vis > 15000  # std of the estimate < 0.0033
    assert 1 - kept / vis == pytest.approx(0.2, abs=0.02)


def test_dropout_never_exposes_a_deeper_surface(sensor):
    # all dropped: nothing is reported, and the shadowed columns stay invisible
    pos, rot = _down()
    pid = torch.zeros(1, dtype=torch.long)
    s = sensor.sense(pos, rot, pid, BONE, torch.Generator().manual_seed(0), missing_rate=1.0)
    assert not s.valid.any() and s.visible.any()
    with pytest.raises(ValueError, match="missing_rate"):
        sensor.sense(pos, rot, pid, BONE, missing_rate=1.5)


def test_same_generator_seed_same_reading(sensor):
    pos, rot = _down(8, x=torch.linspace(-0.01, 0.01, 8, dtype=torch.float64))
    pid = torch.zeros(8, dtype=torch.long)
    a = sensor.sense(pos, rot, pid, BONE, torch.Generator().manual_seed(5))
    b = sensor.sense(pos, rot, pid, BONE, torch.Generator().manual_seed(5))
    c = sensor.sense(pos, rot, pid, BONE, torch.Generator().manual_seed(6))
    assert torch.equal(a.valid, b.valid) and torch.equal(a.points, b.points)
    assert not torch.equal(a.valid, c.valid)


def test_labels_match_the_slicer_on_the_same_pixel_grid(patient):
    # two patients (the second shifted by 3 mm) to exercise the per-env patient lookup
    shifted = Patient(patient.ct, patient.labels, patient.affine.copy(), name="shifted")
    shifted.affine[0, 3] += 0.003
    sensor = BoneSurfaceSensor([patient, shifted])
    geo = ProbeGeometry(80, 50, 1, 1e-3, 1e-3, 1e-3)
    slicer = Slicer([patient, shifted], geo, upsample=False)
    pos, rot = random_poses(12, seed=2, max_angle=0.7)
    pos[:4, 0] += 0.05  # partly outside the volume
    pid = torch.arange(12) % 2
    lab, origin, row_step, col_step = sensor.labels(pos, rot, pid)
    s = slicer(pos, rot, pid)
    assert (lab != s.labels[:, 0]).float().mean() < 1e-3  # exact ties may round either way
    assert torch.allclose(origin, s.origin[:, 0]) and torch.allclose(row_step, s.row_step)
    assert torch.allclose(col_step, s.col_step)
    assert sensor.nbytes < slicer.nbytes / 2
