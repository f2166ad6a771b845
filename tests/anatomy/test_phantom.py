import numpy as np
import pytest
import torch

from sonogym.anatomy import PhantomParams, make_phantom
from sonogym.anatomy import labels as L

SMALL = PhantomParams(spacing=0.002)


def _centroid(p, label):
    idx = torch.nonzero(p.labels == label).double().mean(0).numpy()
    return p.origin + idx * p.spacing


def test_same_seed_same_volumes_bit_for_bit(small_phantom):
    again = make_phantom(0, SMALL)
    assert torch.equal(again.ct, small_phantom.ct)
    assert torch.equal(again.labels, small_phantom.labels)
    other = make_phantom(1, SMALL)
    assert other.meta["params"] != small_phantom.meta["params"]


def test_fixing_one_parameter_keeps_the_other_draws():
    a = PhantomParams(spacing=0.002).resolved(5)
    b = PhantomParams(spacing=0.002, fat_thickness=0.02).resolved(5)
    assert b.fat_thickness == 0.02
    assert a.lordosis == b.lordosis and a.torso_depth == b.torso_depth


def test_every_required_structure_is_present_with_its_id(small_phantom):
    present = set(torch.unique(small_phantom.labels).tolist())
    required = {
        L.SKIN, L.SUBCUTANEOUS_FAT, L.BODY_TRUNC, L.INTERVERTEBRAL_DISCS, L.SPINAL_CANAL,
        L.SPINAL_LIGAMENTS, L.THORACOLUMBAR_FASCIA,
        86, 87, 88, 89,  # autochthon, iliopsoas
        31, 30, 29, 28, 27,  # L1-L5
        32, 26, 25,  # T12, S1, sacrum
        77, 78,  # iliac wings
        2, 3, 5, 52, 63,  # kidneys, liver, aorta, IVC
        79,  # spinal cord
        103, 115,  # 12th ribs
    }  # fmt: skip
    assert required <= present, sorted(required - present)
    assert present <= set(L.LABELS) | {0}


@pytest.mark.parametrize("seed", [0, 3])  # thin, rolled trunks whose iliac crests reached the skin
def test_every_bone_lies_under_the_skin_and_fat(seed, small_phantom):
    p = small_phantom if seed == 0 else make_phantom(seed, PhantomParams(spacing=0.002))
    lab = p.labels.numpy()
    bone = np.isin(lab, sorted(L.BONE_IDS))
    air = lab == 0
    near_air = air.copy()  # within two voxels (4 mm: skin 2.5 mm + fat) of the air, cube
    for axis in range(3):
        for shift in (1, 2):
            near_air |= np.roll(air, shift, axis) | np.roll(air, -shift, axis)
    assert not (bone & near_air).any(), int((bone & near_air).sum())


def test_left_and_right_are_the_patients(small_phantom):
    # RAS+: +x is the patient's right.
    for right, left in ((2, 3), (87, 86), (89, 88), (78, 77), (115, 103)):
        assert _centroid(small_phantom, right)[0] > 0.02
        assert _centroid(small_phantom, left)[0] < -0.02


def test_prone_back_is_the_smallest_y_surface(small_phantom):
    p = small_phantom
    l4 = _centroid(p, 28)
    i, k = np.rint(p.world_to_voxel_np([0.03, 0, l4[2]])[[0, 2]]).astype(int)
    column = p.labels[i, :, k].numpy()
    first = column[column > 0][:3].tolist()
    assert first[0] == L.SKIN  # from the back: skin, then fat
    inside = np.nonzero(column)[0]
    assert p.origin[1] + inside[0] * p.spacing[1] < l4[1] - 0.06  # back well behind the spine
    assert p.origin[1] + inside[-1] * p.spacing[1] > l4[1] + 0.06  # belly in front


def test_field_of_view_covers_120_mm_around_l4(small_phantom):
    z_l4 = _centroid(small_phantom, 28)[2]
    lo, hi = small_phantom.bounds
    assert lo[2] <= z_l4 - 0.12 and hi[2] >= z_l4 + 0.12


def test_l4_dimensions_are_adult(small_phantom):
    lm = small_phantom.landmarks
    f = lm.vertebra("L4")
    pts = torch.nonzero(small_phantom.labels == 28).double().numpy()
    q = (small_phantom.origin + pts * small_phantom.spacing - f.centre) @ f.rotation
    body = q[q[:, 1] > -0.012]  # anterior of the body's back wall
    width, depth, height = np.ptp(body, axis=0)
    assert 0.038 <= width <= 0.056
    assert 0.028 <= depth <= 0.042
    assert 0.022 <= height <= 0.032
    assert 0.018 <= 2 * f.canal_half_width <= 0.030
    assert 0.013 <= 2 * f.canal_half_depth <= 0.022
    assert 0.008 <= lm.trajectory("L4", "right").pedicle_width <= 0.016
    span = np.ptp(q[:, 0])  # transverse-process tip to tip
    assert 0.070 <= span <= 0.100


def test_posterior_soft_tissue_over_the_laminae(small_phantom):
    p = small_phantom
    f = p.landmarks.vertebra("L4")
    bone = (p.labels == 28).numpy()
    for x in (-0.015, 0.015):
        i, k = np.rint(p.world_to_voxel_np([x, 0, f.centre[2]])[[0, 2]]).astype(int)
        col = bone[i, :, k - 3 : k + 4].any(1)
        y_lamina = p.origin[1] + np.argmax(col) * p.spacing[1]
        depth = y_lamina - p.skin.height(torch.tensor(x), torch.tensor(f.centre[2])).item()
        assert 0.030 <= depth <= 0.080, depth


def test_fat_thickness_follows_its_parameter():
    # The fat thickens toward the flanks (fat_lateral), over the buttocks (gluteal, from L3
    # down) and where it fills the midline furrow: fat_thickness is the layer beside the spine
    # above L3, where those terms vanish.
    for fat in (0.008, 0.025):
        p = make_phantom(2, PhantomParams(spacing=0.002, fat_thickness=fat, gluteal=0.0,
                                          fat_lateral=0.0, midline_furrow=1.0))  # fmt: skip
        f = p.landmarks.vertebra("L2")
        i, k = np.rint(p.world_to_voxel_np(f.centre + [0.025, 0, 0])[[0, 2]]).astype(int)
        z = f.centre[2]
        back = p.origin[1] + torch.arange(p.shape[1]) * p.spacing[1] < z * 0  # y < 0: the back
        n_fat = int(((p.labels[i, :, k] == L.SUBCUTANEOUS_FAT) & back).sum())
        assert abs(n_fat * 0.002 - fat) <= 0.004


def test_ct_values_per_tissue_and_partial_volume(small_phantom):
    p = small_phantom
    ct, lab = p.ct, p.labels
    assert abs(ct[lab == L.SUBCUTANEOUS_FAT].median().item() + 100) < 20
    assert abs(ct[lab == 86].median().item() - 50) < 20
    assert (ct == ct.round()).all()  # integer HU: exact int16 round trip
    core = lab == 28
    for _ in range(3):  # erode to the cancellous core
        core = core & torch.roll(core, 1, 0) & torch.roll(core, -1, 0)
        core = core & torch.roll(core, 1, 1) & torch.roll(core, -1, 1)
    canc = p.meta["params"]["cancellous_hu"]
    assert abs(ct[core].median().item() - canc) < 60
    assert ct[lab == 28].max() > 900  # cortical shell
    # skin edge: partial-volume values between air and tissue exist
    edge = (lab == L.SKIN) | (lab == 0)
    mid = ((ct > -800) & (ct < -200) & edge).sum().item()
    assert mid > 100


def test_anatomical_parameters_change_anatomy():
    straight = make_phantom(4, PhantomParams(spacing=0.002, lordosis=0.45, scoliosis=0.0))
    curved = make_phantom(4, PhantomParams(spacing=0.002, lordosis=0.85, scoliosis=0.006))

    def ys(p):
        return [p.landmarks.vertebra(lv).centre for lv in ("L1", "L3", "L5")]

    s, c = ys(straight), ys(curved)
    sag_s = s[1][1] - (s[0][1] + s[2][1]) / 2
    sag_c = c[1][1] - (c[0][1] + c[2][1]) / 2
    assert sag_c > sag_s + 0.002  # more lordosis: L3 further anterior than L1/L5
    assert c[1][0] - (c[0][0] + c[2][0]) / 2 > 0.002  # scoliosis bends the spine to the right


def test_bad_parameters_raise():
    with pytest.raises(ValueError, match="0.5-2.0 mm"):
        PhantomParams(spacing=0.003)
    with pytest.raises(ValueError, match="0.12 m"):
        PhantomParams(fov_inferior=0.05)


@pytest.mark.slow
def test_default_phantom_fits_the_memory_budget():
    p = make_phantom(0)
    assert p.nbytes <= 300e6
    assert np.allclose(p.spacing, 0.001)
