"""Shared fixtures for the robot tests: synthetic backs (no phantom generator needed)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sonogym.anatomy.surface import SkinSurface

SPACING = 0.002  # m, height-map grid


def _grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xs = np.arange(-0.25, 0.25 + 1e-9, SPACING)
    zs = np.arange(-0.25, 0.25 + 1e-9, SPACING)
    x, z = np.meshgrid(xs, zs, indexing="ij")
    return xs, x, z


@pytest.fixture(scope="session")
def curved_back() -> SkinSurface:
    """A prone patient's back around L4 at the origin: skin about 0.10 m posterior (y = -0.10),
    curving anteriorly toward the flanks, a shallow paraspinal groove along the midline and a
    gentle cranio-caudal undulation (lordosis)."""
    xs, x, z = _grid()
    h = -0.10 + 0.8 * x**2 + 0.004 * np.exp(-(x**2) / (2 * 0.015**2)) - 0.01 * np.cos(z / 0.12)
    return SkinSurface(h, xs[0], xs[0], SPACING, SPACING)


@pytest.fixture(scope="session")
def flat_back() -> SkinSurface:
    """A flat back at y = -0.09 m."""
    xs, x, _ = _grid()
    return SkinSurface(np.full_like(x, -0.09), xs[0], xs[0], SPACING, SPACING)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """The robot tests run many small batched ops; with pytest -n 2 on 2 cores, torch's
    intra-op threads only oversubscribe the CPU (measured: several times slower). One thread
    per test process for these modules, restored afterwards."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
