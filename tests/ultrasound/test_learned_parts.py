"""Learned simulator building blocks: networks, histogram matching, augmentation."""

import pytest
import torch

from sonogym.ultrasound.learned import (
    CT_WINDOW_HU,
    HistogramReference,
    PatchDiscriminator,
    UNet,
    UNetConfig,
    down_up,
    random_down_up,
    window_ct,
)

torch.set_num_threads(1)


@pytest.mark.parametrize("depth", [2, 3, 4])
def test_unet_shapes_and_range(depth):
    g = UNet(UNetConfig.from_width(8, depth))
    x = torch.rand(3, 1, 32, 48)
    y = g(x)
    assert y.shape == x.shape
    assert y.min() >= 0 and y.max() <= 1


def test_unet_rejects_indivisible_input():
    with pytest.raises(ValueError, match="divisible"):
        UNet(UNetConfig.from_width(8, 4))(torch.rand(1, 1, 30, 32))


def test_unet_config_round_trip():
    c = UNetConfig.from_width(8, 3)
    assert UNetConfig.from_dict(c.to_dict()) == c
    assert c.channels == (8, 16, 32, 32)


def test_patch_discriminator_shape():
    d = PatchDiscriminator(width=8, n_layers=3)
    out = d(torch.rand(2, 1, 64, 64), torch.rand(2, 1, 64, 64))
    assert out.shape == (2, 1, 6, 6)  # 64 -> 32 -> 16 -> 8 -> 7 -> 6


LEVELS = torch.linspace(0.05, 0.95, 19)


def _quantiles(x, q=LEVELS):
    return torch.quantile(x.flatten().float(), q)


def test_histogram_matching_maps_onto_reference():
    g = torch.Generator().manual_seed(0)
    lo, hi = CT_WINDOW_HU
    # reference: a bimodal "soft tissue + bone" mixture; source: a shifted, narrower Gaussian
    ref_hu = torch.cat(
        [torch.randn(60000, generator=g) * 80 + 40, torch.randn(20000, generator=g) * 200 + 900]
    )
    src_hu = torch.randn(4, 64, 64, generator=g) * 150 + 300
    ref = HistogramReference.fit(ref_hu, bins=256)
    out = ref.match(window_ct(src_hu))
    assert out.shape == src_hu.shape
    # quantiles away from 0.75, where the reference has a gap between its modes
    q = LEVELS[(LEVELS < 0.7) | (LEVELS > 0.8)]
    target = _quantiles(window_ct(ref_hu), q)
    before = (_quantiles(window_ct(src_hu), q) - target).abs().max()
    after = (_quantiles(out, q) - target).abs().max()
    assert before > 0.1
    assert after < 0.01, after  # within ~2.5 bins everywhere
    # empirical CDFs agree (Kolmogorov-Smirnov distance)
    grid = torch.linspace(0, 1, 201)
    cdf = lambda v: (v.flatten()[:, None] <= grid).float().mean(0)  # noqa: E731
    assert (cdf(out) - cdf(window_ct(ref_hu))).abs().max() < 0.02


def test_histogram_matching_per_image_and_monotone():
    g = torch.Generator().manual_seed(1)
    ref = HistogramReference.fit(
        torch.rand(10000, generator=g) * (CT_WINDOW_HU[1] - CT_WINDOW_HU[0]) + CT_WINDOW_HU[0]
    )
    x = torch.stack(
        [torch.rand(32, 32, generator=g) * 0.2, torch.rand(32, 32, generator=g) * 0.2 + 0.6]
    )
    out = ref.match(x, per_image=True)
    for i in range(2):  # each image is spread onto the uniform reference
        q = _quantiles(out[i])
        assert (q - torch.linspace(0.05, 0.95, 19)).abs().max() < 0.03
        order = x[i].flatten().argsort()
        assert torch.all(out[i].flatten()[order].diff() >= -1e-6)  # the LUT is monotone


def test_histogram_reference_state_round_trip():
    ref = HistogramReference.fit(torch.randn(1000) * 300, bins=64)
    ref2 = HistogramReference.from_state_dict(ref.state_dict())
    x = torch.rand(2, 16, 16)
    assert torch.equal(ref.match(x), ref2.match(x))
    with pytest.raises(ValueError):
        HistogramReference(torch.tensor([0.0, 0.5]))


def test_down_up_preserves_shape_and_smooths():
    x = torch.rand(4, 1, 32, 32)
    y = down_up(x, 4)
    assert y.shape == x.shape
    assert y.std() < x.std()
    assert torch.equal(down_up(x, 1), x)


def test_random_down_up_changes_content_and_is_seeded():
    x = torch.rand(8, 1, 32, 32)
    a = random_down_up(x, torch.Generator().manual_seed(3), p=1.0, factors=(2.0, 4.0))
    b = random_down_up(x, torch.Generator().manual_seed(3), p=1.0, factors=(2.0, 4.0))
    assert a.shape == x.shape and torch.equal(a, b)
    assert not torch.isclose(a, x).all(dim=(1, 2, 3)).any()  # every sample changed
    assert torch.equal(random_down_up(x, torch.Generator().manual_seed(3), p=0.0), x)
