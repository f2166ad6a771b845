"""Realism checks of the ``physical`` model: bright bone over a shadow, speckle, depth."""

import dataclasses
import math

import pytest
import torch
from scipy import ndimage
from us_synthetic import FAT, MUSCLE, SOFT, block_patient, layered_patient, straight_down

from sonogym.ultrasound import ModelBasedSimulator, PhysicalModel, Slicer


@pytest.fixture(scope="module")
def homogeneous():
    """20 images of homogeneous soft tissue (raw envelope and display)."""
    p = layered_patient([(0.12, SOFT)], size_xz=(0.2, 0.2))
    sl = Slicer(p)
    pos, rot = straight_down(
        20, x=torch.linspace(-0.05, 0.05, 20), z=torch.linspace(-0.05, 0.05, 20)
    )
    s = sl(pos, rot)
    sim = ModelBasedSimulator("physical")
    roi = (slice(None), 0, slice(20, 190), slice(10, 140))  # 10-95 mm deep, away from the edges
    return sim.simulate_raw(s)[roi], sim.simulate(s)[roi]


def test_envelope_is_rayleigh(homogeneous):
    env, _ = homogeneous
    snr = env.mean() / env.std()
    assert 1.81 < snr < 2.01, snr  # 1.91 +- 0.1


def test_log_compressed_speckle_std(homogeneous):
    env, img = homogeneous
    db_std = (20 * torch.log10(env)).std()
    assert 5.1 < db_std < 6.1, db_std  # 5.6 +- 0.5 dB (Fisher-Tippett: 5.57)
    # the display maps dynamic_range dB to [0, 1]; nothing clips in tissue
    dr = PhysicalModel().dynamic_range
    assert 5.1 < img.std() * dr < 6.1
    assert (img == 0).float().mean() < 0.01 and (img == 1).float().mean() < 0.01


def test_flat_brightness_over_depth_after_tgc(homogeneous):
    env, _ = homogeneous
    bands = env.mean((0, 2)).view(10, 17).mean(1)  # ten 8.5 mm bands from 10 to 95 mm
    assert torch.all((bands / bands.mean() - 1).abs() < 0.15), bands / bands.mean()


def test_without_tgc_soft_tissue_loses_2_alpha_f_per_cm():
    p = layered_patient([(0.12, SOFT)], size_xz=(0.2, 0.2))
    s = Slicer(p)(*straight_down(10, x=torch.linspace(-0.04, 0.04, 10)))
    model = PhysicalModel(tgc_alpha=0.0, large_scale_amplitude=0.0)
    env = ModelBasedSimulator(model).simulate_raw(s)[:, 0, :, 10:140]
    db = 20 * torch.log10(env.pow(2).mean((0, 2)).sqrt())  # mean power per row, in dB
    depth_cm = torch.arange(200) * 0.05
    slope = torch.linalg.lstsq(
        torch.stack([depth_cm[20:190], torch.ones(170)], 1), db[20:190, None]
    ).solution[0, 0]
    expected = -2 * 0.6 * 3.5  # dB/cm: soft tissue 0.6 dB/cm/MHz at 3.5 MHz, round trip
    assert slope.item() == pytest.approx(expected, rel=0.1)


@pytest.fixture(scope="module")
def bone_images():
    p = block_patient(soft_depth=0.015, muscle_depth=0.015, bone_depth=0.012, ct_noise=10.0)
    sl = Slicer(p)
    pos, rot = straight_down(
        6, x=torch.linspace(-0.004, 0.004, 6), z=torch.linspace(-0.02, 0.02, 6)
    )
    sim = ModelBasedSimulator("physical")
    s = sl(pos, rot)
    return sim.simulate(s)[:, 0], sim.simulate_raw(s)[:, 0]


def test_bone_gives_a_bright_line_and_a_shadow(bone_images):
    img, env = bone_images
    surface = 60  # bone top at 30 mm
    cols = slice(45, 105)  # over the 40 mm wide bone block
    above = img[:, surface - 30 : surface - 10, cols].mean()  # 5-15 mm above
    below = img[:, surface + 10 : surface + 30, cols].mean()  # 5-15 mm below
    assert below < 0.2 * above, (below, above)
    # the echo is a thin bright line, >= 15 dB above the speckle mean
    line = env[:, surface - 2 : surface + 3, cols].amax(1).mean()
    speckle = env[:, surface - 30 : surface - 10, cols].mean()
    assert 20 * math.log10(line / speckle) > 15
    assert img[:, surface - 2 : surface + 3, cols].amax(1).mean() > 0.85


def test_bone_echo_amplitude_is_the_reflection_coefficient(bone_images):
    _, env = bone_images
    # muscle (1.68 MRayl) -> bone (6.5 * 2400 / 2200 at 1400 HU): R = 0.62; TGC and
    # attenuation cancel in soft tissue (0.6) but not in 15 mm of muscle (0.96 dB/cm/MHz)
    r = (6.5 * 2400 / 2200 - 1.68) / (6.5 * 2400 / 2200 + 1.68)
    skin_to_soft = 1 - ((1.63 - 1.49) / (1.63 + 1.49)) ** 2
    muscle_extra = 10 ** (-2 * (0.96 - 0.6) * 3.5 * 1.5 / 20)
    soft_to_muscle = 1 - ((1.68 - 1.63) / (1.68 + 1.63)) ** 2
    expected = r * skin_to_soft * soft_to_muscle * muscle_extra
    line = env[:, 58:63, 55:95].amax(1).median()
    assert line.item() == pytest.approx(expected, rel=0.3)


def _fat_over_muscle(slope: float):
    """Fat over muscle, interface at y = 20 mm + slope * x."""
    p = layered_patient([(0.1, MUSCLE)], size_xz=(0.2, 0.2))
    xs = p.origin[0] + p.spacing[0] * torch.arange(p.shape[0], dtype=torch.float64)
    ys = p.origin[1] + p.spacing[1] * torch.arange(p.shape[1], dtype=torch.float64)
    fat = (ys[None, :] >= 0) & (ys[None, :] < 0.02 + slope * xs[:, None])
    lab, ct = p.labels.clone(), p.ct.clone()
    lab[fat] = FAT
    ct[fat] = -100.0
    ct = torch.from_numpy(ndimage.gaussian_filter(ct.numpy(), 0.7))  # partial volume, like a CT
    return type(p)(ct, lab, p.affine, name=f"oblique{slope}")


def test_oblique_interfaces_reflect_less():
    """A fat/muscle interface tilted 45 degrees echoes much less than a flat one: cos(theta)
    (1/sqrt(2)) times the loss of lateral PSF support along a slanted line."""
    quiet = PhysicalModel(backscatter_level=-80.0, large_scale_amplitude=0.0)
    sim = ModelBasedSimulator(quiet)
    pos, rot = straight_down(1)
    echo = {}
    for slope in (0.0, 1.0):
        env = sim.simulate_raw(Slicer(_fat_over_muscle(slope))(pos, rot))[0, 0]
        echo[slope] = env.amax(0)[40:110].median()  # strongest echo of each column
    ratio = echo[1.0] / echo[0.0]
    assert 0.25 < ratio < 0.6, ratio


def test_air_gap_gives_no_signal_below():
    p = layered_patient([(0.06, SOFT)], air_above=0.03)
    sl = Slicer(p)
    sim = ModelBasedSimulator("physical")
    on = sim.simulate(sl(*straight_down(1)))
    off = sim.simulate(sl(*straight_down(1, y=-0.01)))  # 10 mm of air under the probe
    assert on[0, 0, 20:110].mean() > 0.2
    assert off[0, 0, 21:].max() == 0.0  # nothing below the gap (>= 10.5 mm)


def test_gel_band_couples_a_probe_barely_off_the_skin():
    p = layered_patient([(0.06, SOFT)], air_above=0.03)
    sl = Slicer(p)
    sim = ModelBasedSimulator("physical")
    touching = sim.simulate(sl(*straight_down(1)))
    hovering = sim.simulate(sl(*straight_down(1, y=-0.002)))  # 2 mm gap: inside the gel band
    a, b = hovering[0, 0, 20:100].mean(), touching[0, 0, 20:100].mean()
    assert float(a) == pytest.approx(float(b), rel=0.15)


def test_fluid_is_anechoic():
    p = layered_patient([(0.02, SOFT), (0.02, 122), (0.04, SOFT)], size_xz=(0.2, 0.2))
    s = Slicer(p)(*straight_down(4, x=torch.linspace(-0.03, 0.03, 4)))
    env = ModelBasedSimulator(dataclasses.replace(PhysicalModel())).simulate_raw(s)[:, 0]
    tissue, fluid = env[:, 10:36].mean(), env[:, 46:76].mean()
    assert 20 * math.log10(fluid / tissue) < -20
