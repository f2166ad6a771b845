"""Synthetic patients and probe poses for the ultrasound tests (no phantom generator needed)."""

from __future__ import annotations

import numpy as np
import torch

from sonogym.anatomy.patient import Patient

AIR, SOFT, MUSCLE, FAT, BONE = 0, 120, 86, 119, 28
HU = {AIR: -1000.0, SOFT: 40.0, MUSCLE: 50.0, FAT: -100.0, BONE: 1400.0, 122: 10.0}


def layered_patient(
    layers: list[tuple[float, int]],
    spacing: float = 1e-3,
    size_xz: tuple[float, float] = (0.12, 0.12),
    air_above: float = 0.01,
    name: str = "layers",
    ct_noise: float = 0.0,
    seed: int = 0,
) -> Patient:
    """A box patient whose tissue depends on y only (y = depth into the back, skin at y = 0).

    layers: (thickness in m, label) from the skin down; HU from ``HU``. Air fills y < 0.
    The patient frame origin sits at the volume's centre in x and z.
    """
    nx, nz = (round(s / spacing) for s in size_xz)
    ny_air = round(air_above / spacing)
    ny = ny_air + sum(round(t / spacing) for t, _ in layers)
    lab = np.zeros((nx, ny, nz), np.uint8)
    y = ny_air
    for t, label in layers:
        k = round(t / spacing)
        lab[:, y : y + k] = label
        y += k
    ct = np.vectorize(HU.get)(lab).astype(np.float32)
    if ct_noise:
        ct += np.random.default_rng(seed).normal(0, ct_noise, ct.shape).astype(np.float32)
    aff = np.diag([spacing, spacing, spacing, 1.0])
    # voxel centre (i, ny_air - 0.5, k) is the skin plane y = 0; x, z centred
    aff[:3, 3] = [-(nx - 1) / 2 * spacing, -(ny_air - 0.5) * spacing, -(nz - 1) / 2 * spacing]
    return Patient(torch.from_numpy(ct), torch.from_numpy(lab), aff, name=name)


def block_patient(
    spacing: float = 1e-3,
    soft_depth: float = 0.02,
    muscle_depth: float = 0.015,
    bone_depth: float = 0.012,
    below: float = 0.06,
    bone_width: float = 0.04,
    name: str = "block",
    ct_noise: float = 10.0,
    seed: int = 0,
) -> Patient:
    """Soft tissue, then muscle, then a bone block of limited lateral width (x in
    [-bone_width/2, bone_width/2]) inside muscle, then soft tissue below. Skin at y = 0."""
    p = layered_patient(
        [(soft_depth, SOFT), (muscle_depth + bone_depth, MUSCLE), (below, SOFT)],
        spacing,
        name=name,
    )
    lab = p.labels.numpy().copy()
    xs = p.origin[0] + spacing * np.arange(lab.shape[0])
    ys = p.origin[1] + spacing * np.arange(lab.shape[1])
    bx = np.abs(xs) <= bone_width / 2
    by = (ys >= soft_depth + muscle_depth) & (ys < soft_depth + muscle_depth + bone_depth)
    lab[np.ix_(bx, by, np.ones(lab.shape[2], bool))] = BONE
    ct = np.vectorize(HU.get)(lab).astype(np.float32)
    if ct_noise:
        ct += np.random.default_rng(seed).normal(0, ct_noise, ct.shape).astype(np.float32)
        ct[lab == AIR] = HU[AIR]
    return Patient(torch.from_numpy(ct), torch.from_numpy(lab), p.affine, name=name)


def straight_down(n: int = 1, x=0.0, z=0.0, y=0.0, dtype=torch.float64):
    """n probe poses on the skin plane y = 0 looking along +y, lateral axis +x.

    x, z: scalars or (n,) offsets in metres."""
    pos = torch.zeros(n, 3, dtype=dtype)
    pos[:, 0] = torch.as_tensor(x, dtype=dtype)
    pos[:, 1] = torch.as_tensor(y, dtype=dtype)
    pos[:, 2] = torch.as_tensor(z, dtype=dtype)
    rot = torch.tensor([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=dtype).expand(n, 3, 3).clone()
    return pos, rot


def random_poses(n: int, seed: int = 0, spread: float = 0.02, max_angle: float = 0.6):
    """n probe poses near (0, 0, 0), beam roughly along +y, random in-plane and tilt angles."""
    from sonogym.geometry import matrix_from_axis_angle

    g = torch.Generator().manual_seed(seed)
    pos = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * spread
    pos[:, 1] = 0.0
    base = straight_down(n)[1]
    aa = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * 2 * max_angle
    return pos, matrix_from_axis_angle(aa) @ base
