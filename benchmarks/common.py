"""Helpers shared by the benchmark scripts (run as ``python benchmarks/<name>.py``, so this
folder is on ``sys.path``)."""

from __future__ import annotations

import torch


def surface_poses(patient, n: int, seed: int = 0):
    """n random surface poses around L4 (the navigation task's 130 x 130 mm, yaw 1.5-3.5)."""
    c = patient.landmarks.vertebra("L4").centre
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 3, generator=g, dtype=torch.float64)
    x = c[0] + (u[:, 0] - 0.5) * 0.13
    z = c[2] + (u[:, 1] - 0.5) * 0.13
    yaw = 1.5 + 2.0 * u[:, 2]
    return patient.skin.surface_pose(x, z, yaw)
