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
