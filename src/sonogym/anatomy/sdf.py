"""Signed-distance primitives (torch, broadcasting) used to draw the procedural phantom.

Negative inside, positive outside, in millimetres. Ellipse/ellipsoid/superellipse distances are
first-order approximations (exact on the surface, close nearby), which is all partial-volume
rendering and layer thicknesses need.
"""

from __future__ import annotations

import torch

Tensor = torch.Tensor


def ellipse2(u: Tensor, v: Tensor, ru: float, rv: float) -> Tensor:
    """Ellipse with semi-axes (ru, rv) centred at the origin."""
    k0 = torch.sqrt((u / ru) ** 2 + (v / rv) ** 2)
    k1 = torch.sqrt((u / ru**2) ** 2 + (v / rv**2) ** 2).clamp_min(1e-6)
    return k0 * (k0 - 1) / k1


def superellipse2(u: Tensor, v: Tensor, ru: float, rv: float, n: float) -> Tensor:
    """Superellipse |u/ru|^n + |v/rv|^n = 1 (n > 2 gives flatter sides), distance F-1 / |grad F|."""
    a = (u.abs() / ru).clamp_min(1e-9)
    b = (v.abs() / rv).clamp_min(1e-9)
    f = (a**n + b**n) ** (1 / n)
    g = f ** (1 - n) * torch.sqrt((a ** (n - 1) / ru) ** 2 + (b ** (n - 1) / rv) ** 2)
    return (f - 1) / g.clamp_min(1e-9)


def ellipsoid(dx: Tensor, dy: Tensor, dz: Tensor, rx: float, ry: float, rz: float) -> Tensor:
    """Ellipsoid with semi-axes (rx, ry, rz) centred at the origin."""
    k0 = torch.sqrt((dx / rx) ** 2 + (dy / ry) ** 2 + (dz / rz) ** 2)
    k1 = torch.sqrt((dx / rx**2) ** 2 + (dy / ry**2) ** 2 + (dz / rz**2) ** 2).clamp_min(1e-6)
    return k0 * (k0 - 1) / k1


def extrude(d2: Tensor, w: Tensor, half: float) -> Tensor:
    """Extrude a 2-D distance ``d2`` along a third coordinate ``w`` over [-half, half]."""
    qx, qy = d2, w.abs() - half
    outside = torch.sqrt(qx.clamp_min(0) ** 2 + qy.clamp_min(0) ** 2)
    return outside + torch.minimum(torch.maximum(qx, qy), torch.zeros_like(qx))


def segment2(u: Tensor, v: Tensor, a: tuple[float, float], b: tuple[float, float]) -> Tensor:
    """Unsigned distance from (u, v) to the 2-D segment a-b."""
    bu, bv = b[0] - a[0], b[1] - a[1]
    pu, pv = u - a[0], v - a[1]
    t = ((pu * bu + pv * bv) / max(bu * bu + bv * bv, 1e-12)).clamp(0, 1)
    return torch.sqrt((pu - t * bu) ** 2 + (pv - t * bv) ** 2)


def capsule(
    x: Tensor, y: Tensor, z: Tensor, a: tuple[float, ...], b: tuple[float, ...], r: float
) -> Tensor:
    """Capsule of radius r around the 3-D segment a-b."""
    bx, by, bz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    px, py, pz = x - a[0], y - a[1], z - a[2]
    t = ((px * bx + py * by + pz * bz) / max(bx * bx + by * by + bz * bz, 1e-12)).clamp(0, 1)
    return torch.sqrt((px - t * bx) ** 2 + (py - t * by) ** 2 + (pz - t * bz) ** 2) - r


def smooth_union(a: Tensor, b: Tensor, k: float) -> Tensor:
    """Union that blends the two shapes over a fillet of size k (mm)."""
    h = (k - (a - b).abs()).clamp_min(0) / k
    return torch.minimum(a, b) - h * h * k / 4


def smooth_subtract(a: Tensor, b: Tensor, k: float) -> Tensor:
    """``a`` with ``b`` carved out, the cut edge blended over a fillet of size k (mm)."""
    return -smooth_union(-a, b, k)


def round_box(
    u: Tensor, v: Tensor, w: Tensor, half: tuple[float, float, float], r: float = 0.0
) -> Tensor:
    """Box with half-sizes ``half`` centred at the origin of (u, v, w), edges rounded by r
    (the rounding stays inside the half-sizes)."""
    qu = u.abs() - (half[0] - r)
    qv = v.abs() - (half[1] - r)
    qw = w.abs() - (half[2] - r)
    outside = torch.sqrt(qu.clamp_min(0) ** 2 + qv.clamp_min(0) ** 2 + qw.clamp_min(0) ** 2)
    return outside + torch.maximum(torch.maximum(qu, qv), qw).clamp_max(0) - r


def polygon2(u: Tensor, v: Tensor, pts: list[tuple[float, float]]) -> Tensor:
    """Exact signed distance to a simple polygon with vertices ``pts`` (either winding)."""
    n = len(pts)
    d2 = None
    inside = torch.zeros_like(u, dtype=torch.bool)
    for i in range(n):
        a, b = pts[i], pts[i - 1]
        seg = segment2(u, v, a, b) ** 2
        d2 = seg if d2 is None else torch.minimum(d2, seg)
        # even-odd rule: does the horizontal ray from (u, v) cross edge a-b?
        if a[1] != b[1]:
            crosses = (v >= min(a[1], b[1])) & (v < max(a[1], b[1]))
            x_at = a[0] + (v - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
            inside ^= crosses & (u < x_at)
    d = torch.sqrt(d2)
    return torch.where(inside, -d, d)
