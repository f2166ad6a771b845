import pytest
import torch

from sonogym.ultrasound import ProbeGeometry


def test_linear_2d_is_the_papers_probe():
    p = ProbeGeometry.linear_2d()
    assert p.shape == (1, 200, 150)
    assert p.depth_spacing == p.width_spacing == 0.5e-3
    assert p.depth == pytest.approx(0.1) and p.width == pytest.approx(0.075)
    x = p.lateral_positions()
    assert x[0] == pytest.approx(-x[-1]) and x[1] - x[0] == pytest.approx(0.5e-3)
    assert p.depth_positions()[0] == 0.0


def test_volume_3d_slices_at_minus_20_to_20_mm():
    p = ProbeGeometry.volume_3d()
    assert p.shape == (5, 50, 37)
    assert (p.depth_spacing, p.width_spacing, p.elevation_spacing) == (2e-3, 2e-3, 10e-3)
    torch.testing.assert_close(
        p.elevation_positions(), torch.tensor([-0.02, -0.01, 0.0, 0.01, 0.02], dtype=torch.float64)
    )


@pytest.mark.parametrize(
    "kwargs",
    [{"depth_px": 0}, {"width_px": 2.5}, {"depth_spacing": 0.5}, {"width_spacing": -1e-3}],
)
def test_bad_geometry_raises(kwargs):
    with pytest.raises(ValueError, match="ProbeGeometry"):
        ProbeGeometry(**kwargs)


def test_probe_is_hashable_and_frozen():
    p = ProbeGeometry.linear_2d()
    assert {p: 1}[ProbeGeometry.linear_2d()] == 1
    with pytest.raises(AttributeError):
        p.depth_px = 3
