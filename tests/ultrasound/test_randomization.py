"""Imaging randomisation: nominal settings reproduce the simulator's own display, and each knob
does to the display what its definition says (dB shifts, depth ramps, zoom, blur)."""

from __future__ import annotations

import math

import pytest
import torch
from us_synthetic import block_patient, random_poses

from sonogym.ultrasound import ModelBasedSimulator, ProbeGeometry, Slicer
from sonogym.ultrasound import randomization as R

PROBE = ProbeGeometry.linear_2d()


@pytest.fixture(scope="module")
def slices():
    patient = block_patient(ct_noise=10.0)
    pos, rot = random_poses(4, seed=3)
    return Slicer(patient, PROBE)(pos, rot)


def _settings(n: int, **values) -> torch.Tensor:
    s = R.nominal(n, PROBE, 60.0)
    cols = {"gain": 0, "dr": 1, "tgc_top": 2, "tgc_mid": 3, "tgc_bottom": 4, "att": 5,
            "blur": 6, "depth": 7}  # fmt: skip
    for k, v in values.items():
        s[:, cols[k]] = v
    return s


def test_nominal_settings_reproduce_the_physical_display(slices):
    sim = ModelBasedSimulator("physical")
    display = sim.simulate(slices)
    raw = sim.simulate_raw(slices)
    again = R.randomized_display(raw, _settings(4), PROBE, sim.model.gain)
    assert (again - display).abs().max() < 2e-5


def test_nominal_settings_leave_another_simulators_display_alone(slices):
    img = ModelBasedSimulator("reference").simulate(slices)
    assert (R.randomized_from_display(img, _settings(4), PROBE) - img).abs().max() < 1e-6


def test_gain_tgc_and_attenuation_add_their_db_per_row(slices):
    sim = ModelBasedSimulator("physical")
    raw = sim.simulate_raw(slices)
    base = R.randomized_display(raw, _settings(4), PROBE)
    h = PROBE.depth_px
    rows = torch.arange(h, dtype=torch.float32)
    depth_cm = rows * PROBE.depth_spacing * 1e2
    tgc = torch.where(rows <= (h - 1) / 2, rows / ((h - 1) / 2), 1.0) * 4.0  # 0 -> 4 dB mid
    expect_db = 3.0 + tgc - 1.5 * depth_cm  # gain + TGC(d) - attenuation * d
    out = R.randomized_display(raw, _settings(4, gain=3.0, tgc_mid=4.0, tgc_bottom=4.0, att=1.5),
                               PROBE)  # fmt: skip
    inside = (base > 0.05) & (base < 0.95) & (out > 0.05) & (out < 0.95)  # not clipped
    shift = (out - base) * 60.0  # dB
    want = expect_db.view(1, 1, h, 1).expand_as(shift)
    assert inside.sum() > 1000
    assert (shift[inside] - want[inside]).abs().max() < 1e-3


def test_dynamic_range_scales_the_db_below_the_top(slices):
    raw = ModelBasedSimulator("physical").simulate_raw(slices)
    a = R.randomized_display(raw, _settings(4, dr=60.0), PROBE)
    b = R.randomized_display(raw, _settings(4, dr=40.0), PROBE)
    ok = (a > 0.4) & (a < 0.99)
    # y = 1 + dB / DR: (1 - y) DR is the same dB
    assert ((1 - a[ok]) * 60 - (1 - b[ok]) * 40).abs().max() < 1e-3


def test_depth_shows_the_top_of_the_image_over_all_rows(slices):
    raw = ModelBasedSimulator("physical").simulate_raw(slices)
    full = R.randomized_display(raw, _settings(4), PROBE)
    zoom = R.randomized_display(raw, _settings(4, depth=0.8 * PROBE.depth), PROBE)
    # row 5 k shows source row 4 k exactly (0.8 * 5 k)
    for k in (0, 10, 39):
        assert torch.allclose(zoom[:, :, 5 * k], full[:, :, 4 * k], atol=1e-4)  # float32 scale
    half = R.randomized_display(raw, _settings(4, depth=0.5 * PROBE.depth), PROBE)
    assert torch.allclose(half[:, :, 3], 0.5 * (full[:, :, 1] + full[:, :, 2]), atol=1e-4)


def test_speckle_blur_widens_the_grain_and_keeps_the_mean():
    g = torch.Generator().manual_seed(0)
    env = torch.randn(2, 1, 200, 150, generator=g).abs() + 0.5  # uncorrelated "speckle"
    blurred = R._blend_speckle(env, torch.tensor([0.0, 1.0]), PROBE)
    assert torch.equal(blurred[0], env[0])
    inner = (slice(None), slice(10, -10), slice(10, -10))
    assert blurred[1][inner].mean() == pytest.approx(env[1][inner].mean().item(), rel=1e-3)

    def lag1(x):  # correlation of neighbouring pixels along depth
        x = x[inner] - x[inner].mean()
        return float((x[:, 1:] * x[:, :-1]).mean() / (x * x).mean())

    assert abs(lag1(env[1])) < 0.05 and lag1(blurred[1]) > 0.6


def test_draws_fill_their_ranges_and_bad_ranges_are_refused():
    ranges = R.ImagingRandomization()
    u = torch.rand(4000, 8, generator=torch.Generator().manual_seed(1))
    s = ranges.draw(u)
    for i, name in enumerate(R.ImagingRandomization.COLUMNS):
        lo, hi = getattr(ranges, name)
        assert lo <= s[:, i].min() and s[:, i].max() <= hi
        assert s[:, i].max() - s[:, i].min() > 0.95 * (hi - lo)
    assert R.imaging_ranges(True) == ranges and R.imaging_ranges(False) is None
    assert R.imaging_ranges({"gain_db": [-1, 1]}).gain_db == (-1.0, 1.0)
    with pytest.raises(ValueError, match="low <= high"):
        R.ImagingRandomization(gain_db=(3.0, -3.0))
    with pytest.raises(ValueError, match="unknown settings"):
        R.imaging_ranges({"brightness": (0, 1)})
    with pytest.raises(ValueError, match="low <= high"):
        R.ImagingRandomization(depth=(0.08, math.nan))
