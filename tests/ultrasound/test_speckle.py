import math

import pytest
import torch

from sonogym.ultrasound.speckle import gaussian_quantiles, lattice_bits, seed_mix

CELL = 0.5e-3


def _planes(angles, origin=(0.01, 0.0, 0.02)):
    b = len(angles)
    ang = torch.tensor(angles, dtype=torch.float64)
    org = torch.tensor([origin] * b, dtype=torch.float64)
    rows = torch.tensor([[0.0, 1.0, 0.0]] * b, dtype=torch.float64) * CELL
    cols = torch.stack([torch.cos(ang), torch.zeros(b), torch.sin(ang)], 1) * CELL
    return org, rows, cols


def _uniform(h, bits=0, n=10):
    return ((h >> bits) & (2**n - 1)).double() / 2**n


def test_bits_are_deterministic_and_seeded():
    org, rows, cols = _planes([0.0, 0.7])
    mix = seed_mix(torch.tensor([3, 3]))
    a = lattice_bits(org, rows, cols, 64, 48, CELL, mix)
    b = lattice_bits(org, rows, cols, 64, 48, CELL, mix)
    assert torch.equal(a, b)
    c = lattice_bits(org, rows, cols, 64, 48, CELL, seed_mix(torch.tensor([4, 4])))
    assert (a == c).float().mean() < 0.01
    ua, uc = _uniform(a), _uniform(c)
    corr = torch.corrcoef(torch.stack([ua.flatten(), uc.flatten()]))[0, 1]
    assert abs(corr) < 0.03


def test_noise_is_fixed_in_patient_space():
    org, rows, cols = _planes([0.0])
    mix = seed_mix(torch.tensor([1]))
    a = lattice_bits(org, rows, cols, 40, 30, CELL, mix)
    # one cell to the right and two rows down: the same lattice points, shifted
    b = lattice_bits(org + cols + 2 * rows, rows, cols, 40, 30, CELL, mix)
    assert torch.equal(a[:, 2:, 1:], b[:, :-2, :-1])
    # a sub-cell shift keeps most pixels on the same lattice point
    c = lattice_bits(org + 0.2 * cols, rows, cols, 40, 30, CELL, mix)
    assert (a == c).float().mean() > 0.6


@pytest.mark.parametrize("angle", [0.0, math.pi / 2, 0.3, 1.1])
def test_bits_are_uniform_and_uncorrelated_between_neighbours(angle):
    org, rows, cols = _planes([angle])
    h = lattice_bits(org, rows, cols, 200, 150, CELL, seed_mix(torch.tensor([7])))
    for shift in (0, 12, 22):
        u = _uniform(h, shift)[0]
        assert u.mean() == pytest.approx(0.5, abs=0.01)
        assert (u.var() * 12).item() == pytest.approx(1.0, abs=0.03)
        x = u - u.mean()
        for dj, di in ((1, 0), (0, 1), (1, 1), (0, 2)):
            c = (x[dj:, di:] * x[: x.shape[0] - dj, : x.shape[1] - di]).mean() / x.var()
            # on rotated planes neighbours sometimes share a lattice point (nearest lookup)
            limit = 0.04 if angle in (0.0, math.pi / 2) else 0.3
            assert abs(c) < limit


def test_bit_fields_are_independent():
    org, rows, cols = _planes([0.4])
    h = lattice_bits(org, rows, cols, 200, 150, CELL, seed_mix(torch.tensor([9])))
    fields = torch.stack([_uniform(h, s).flatten() for s in (0, 12, 22)])
    c = torch.corrcoef(fields)
    assert (c - torch.eye(3)).abs().max() < 0.02


def test_out_of_range_positions_raise():
    org, rows, cols = _planes([0.0], origin=(5.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="noise lattice"):
        lattice_bits(org, rows, cols, 4, 4, CELL, seed_mix(torch.tensor([0])))


def test_gaussian_quantiles():
    q = gaussian_quantiles(10)
    assert q.shape == (1024,)
    assert q.mean().abs() < 1e-6 and q.pow(2).mean() == pytest.approx(1.0, abs=1e-5)
    assert torch.all(q[1:] > q[:-1])


def test_seed_mix_is_splitmix64_bit_for_bit_without_a_host_loop():
    from sonogym.ultrasound.speckle import splitmix64

    s = torch.randint(0, 2**31, (2000,), generator=torch.Generator().manual_seed(0))
    s[:3] = torch.tensor([0, 1, 2**31 - 1])
    for salt in (0, 12345, 2**40):
        want = torch.tensor([splitmix64(int(v) * 1000003 + salt) for v in s.tolist()])
        assert torch.equal(seed_mix(s, salt), want)
    # elementwise: any shape gives the same keys
    assert torch.equal(seed_mix(s.view(40, 50)).view(-1), seed_mix(s))
