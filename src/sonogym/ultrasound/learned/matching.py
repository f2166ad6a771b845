"""The CT sample the learned simulator's histogram matching is fitted on.

The LUT that maps a scene's CT onto each net's training CT is fitted once, when the simulator is
built for the scene, on CT slices at fixed pseudo-random probe poses over every patient's lower
back, so images are deterministic per pose and independent of the batch.
"""

from __future__ import annotations

import numpy as np
import torch


def matching_sample(patients, device, per_patient: int = 32, seed: int = 0) -> torch.Tensor:
    """CT (HU) of ``per_patient`` 100 x 75 mm slices at 1 mm per patient, at probe poses drawn
    like the training pairs' (x within +-40 mm of the midline, z over the lumbar region, any
    yaw, tilt within +-0.25 rad) from a fixed seed."""
    from sonogym.ultrasound import ProbeGeometry, Slicer

    rng = np.random.default_rng(seed)
    slicer = Slicer(list(patients), ProbeGeometry.linear_2d(100, 75, 1e-3), device=device)
    cts = []
    for i, p in enumerate(patients):
        lo, hi = p.bounds
        z_lo, z_hi = max(lo[2] + 0.03, -0.10), min(hi[2] - 0.03, 0.12)
        m = per_patient
        x = torch.from_numpy(rng.uniform(-0.04, 0.04, m)).to(device)
        z = torch.from_numpy(rng.uniform(z_lo, z_hi, m)).to(device)
        yaw = torch.from_numpy(rng.uniform(0, 2 * np.pi, m)).to(device)
        tilt = torch.from_numpy(rng.uniform(-0.25, 0.25, m)).to(device)
        pos, rot = p.skin.to(device).surface_pose(x, z, yaw, tilt)
        pid = torch.full((m,), i, dtype=torch.long, device=device)
        cts.append(slicer(pos.float(), rot.float(), pid).ct)
    return torch.cat(cts)
