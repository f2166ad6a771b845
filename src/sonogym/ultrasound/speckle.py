"""Stateless speckle noise fixed in patient space.

The scatterer noise at a pixel is a hash of the patient-frame lattice point nearest to the pixel
(lattice spacing ``cell``, 0.5 mm by default, like the reference's noise maps) and of the
patient's speckle seed. Nothing is stored per patient (the reference keeps an 830 MB random
volume per patient): the same pose always gives the same noise, a small probe motion shifts the
noise with the anatomy, and a different seed gives a different, independent patient.

Hashing runs on every pixel, so it is built from a few full-array integer operations:

* pixel (j, i) of an image lies at ``origin + j * row_step + i * col_step``; its lattice
  coordinates are ``a(j) + b(i)`` per axis, with the row part a and the column part b computed
  on the small (B, H) and (B, W) grids;
* a and b are stored in fixed point (``FRAC_BITS`` fractional bits) and the three axes are
  packed into one int64 (``FIELD_BITS`` per axis, no carries between fields), so one broadcast
  integer addition gives the packed lattice coordinates of every pixel and one mask drops the
  fractions;
* the packed key, xor the seed, is folded to 32 bits and goes through MurmurHash3's 32-bit
  finaliser (logical xor-shifts and wrapping int32 multiplies, the same on CPU and CUDA:
  neighbouring pixels' bits are uncorrelated, tests/ultrasound/test_speckle.py); the result is
  the pixel's 32 random bits.

Range: lattice coordinates span 2^(FIELD_BITS - FRAC_BITS) cells (4 m at 0.5 mm) centred on the
patient frame's origin.
"""

from __future__ import annotations

import math

import torch

from sonogym.checks import expect_all

FRAC_BITS = 8
FIELD_BITS = 21
_INT_BITS = FIELD_BITS - FRAC_BITS
_OFFSET = 2 ** (_INT_BITS - 1)  # cells; lattice coordinate 0 sits at -_OFFSET cells
_FIELD_MAX = 2**FIELD_BITS
_FRAC_MASK = (
    (2**FRAC_BITS - 1)
    | ((2**FRAC_BITS - 1) << FIELD_BITS)
    | ((2**FRAC_BITS - 1) << (2 * FIELD_BITS))
)
_INT_MASK = (2 ** (3 * FIELD_BITS) - 1) ^ _FRAC_MASK


def _signed(x: int) -> int:
    """A 64-bit constant as a signed int64."""
    x &= 2**64 - 1
    return x - 2**64 if x >= 2**63 else x


# MurmurHash3's 32-bit finaliser constants, as signed int32.
_M32_1 = 0x85EBCA6B - 2**32
_M32_2 = 0xC2B2AE35 - 2**32


def splitmix64(x: int) -> int:
    """A well-mixed signed 64-bit integer from any int (per-patient seed mixing, host side)."""
    x = (x + 0x9E3779B97F4A7C15) & (2**64 - 1)
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & (2**64 - 1)
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & (2**64 - 1)
    return _signed(x ^ (x >> 31))


def _shift_right(x: torch.Tensor, k: int) -> torch.Tensor:
    """Logical (unsigned) right shift of int64 ``x`` by ``k`` bits (torch's ``>>`` is
    arithmetic)."""
    return (x >> k) & ((1 << (64 - k)) - 1)


def seed_mix(seed: torch.Tensor, salt: int = 0) -> torch.Tensor:
    """(B,) int64 seeds in [0, 2^31) -> (B,) well-mixed int64 keys (``salt`` separates
    independent fields): ``splitmix64(seed * 1000003 + salt)`` bit for bit, on the tensor's
    device (int64 products wrap modulo 2^64 as splitmix64's do), with no host round trip."""
    x = seed.to(torch.int64) * 1000003 + (salt + _signed(0x9E3779B97F4A7C15))
    x = (x ^ _shift_right(x, 30)) * _signed(0xBF58476D1CE4E5B9)
    x = (x ^ _shift_right(x, 27)) * _signed(0x94D049BB133111EB)
    return x ^ _shift_right(x, 31)


def hash_bits(
    rows: torch.Tensor,
    cols: torch.Tensor,
    mix: torch.Tensor,
    out: torch.Tensor | None = None,
    tmp: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, H, W) int32 random values from packed coordinates and (B,) mixed seeds.

    ``out`` (int32) and ``tmp`` (int64) are optional (B, H, W) buffers. The packed key (int64)
    is xor-ed with the seed and folded to 32 bits (low word xor high word: distinct lattice
    points collide only 0.5 m or more apart), then mixed with MurmurHash3's 32-bit finaliser."""
    shape = (rows.shape[0], rows.shape[1], cols.shape[1])
    key = torch.add(rows[:, :, None], cols[:, None, :], out=tmp)
    key.bitwise_and_(_INT_MASK)
    key.bitwise_xor_(mix.view(-1, 1, 1))
    if out is None:
        out = torch.empty(shape, dtype=torch.int32, device=key.device)
    words = key.view(torch.int32).view(*shape, 2)  # little-endian: (low, high)
    h = torch.bitwise_xor(words[..., 0], words[..., 1], out=out)
    t = key.view(torch.int32).view(-1)[: h.numel()].view(shape)  # key's storage is free now
    for shift, mult in ((16, _M32_1), (13, _M32_2), (16, None)):
        # logical shift (torch's >> is arithmetic on signed ints): mask the sign copies away
        torch.bitwise_right_shift(h, shift, out=t).bitwise_and_(2 ** (32 - shift) - 1)
        h.bitwise_xor_(t)
        if mult is not None:
            h.mul_(mult)
    return h


def lattice_bits(
    origin: torch.Tensor,
    row_step: torch.Tensor,
    col_step: torch.Tensor,
    height: int,
    width: int,
    cell: float,
    mix: torch.Tensor,
    out: torch.Tensor | None = None,
    tmp: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, H, W) int32 random values, a function of each pixel's nearest lattice point and the
    image's seed only.

    Args:
        origin: (B, 3) position of pixel (0, 0), metres (float64).
        row_step, col_step: (B, 3) displacement per row / column, metres.
        height, width: image size in pixels.
        cell: lattice spacing, metres.
        mix: (B,) mixed seeds (``seed_mix``).
        out, tmp: optional (B, H, W) int32 and int64 buffers (``hash_bits``).
    """
    # Packed fixed-point lattice coordinates: rows (B, H) and cols (B, W) int64 such that
    # (rows[:, :, None] + cols[:, None, :]) & _INT_MASK identifies every pixel's lattice point.
    dev = origin.device
    o = origin.double() / cell
    r = row_step.double() / cell
    c = col_step.double() / cell
    j = torch.arange(height, dtype=torch.float64, device=dev)
    i = torch.arange(width, dtype=torch.float64, device=dev)
    a = o[:, None, :] + j[None, :, None] * r[:, None, :] + (0.5 + _OFFSET)  # (B, H, 3)
    b = i[None, :, None] * c[:, None, :]  # (B, W, 3)
    bmin = b.amin(1, keepdim=True)
    a = a + bmin
    b = b - bmin
    scale = float(2**FRAC_BITS)
    afx = torch.floor(a * scale).long()
    bfx = torch.floor(b * scale).long()
    lo = afx.amin()
    hi = afx.amax(1).unsqueeze(1) + bfx.amax(1).unsqueeze(1)
    expect_all(
        (lo >= 0) & (hi.max() < _FIELD_MAX),
        "speckle: pixel positions lie beyond the noise lattice's range "
        f"(+-{_OFFSET * cell:.2f} m around the patient origin)",
    )
    shifts = (2 * FIELD_BITS, FIELD_BITS, 0)
    rows = sum(afx[..., k] << s for k, s in enumerate(shifts))
    cols = sum(bfx[..., k] << s for k, s in enumerate(shifts))
    return hash_bits(rows, cols, mix, out, tmp)


def gaussian_quantiles(bits: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(2**bits,) standard-normal quantiles at (k + 0.5) / 2**bits: a table that turns uniform
    random bits into N(0, 1) samples, scaled to unit variance."""
    n = 2**bits
    p = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    q = math.sqrt(2.0) * torch.erfinv(2 * p - 1)
    q = q / q.pow(2).mean().sqrt()  # exact unit variance despite the quantisation
    return q.to(dtype=dtype, device=device)
