"""The envs' ultrasound simulator: model-based or the learned nets, one interface.

``simulator="physical"`` / ``"sonogym"``: ``ModelBasedSimulator`` with that ultrasound model.
``"learned"``: a ``LearnedSimulator`` over the nets of ``learned_nets`` (ints: shipped nets by
index, strings: paths to ``generator.pt`` files). Like the paper, each env draws one net of the set
uniformly at every episode reset, from the env's seeded generator (``NetChoice``), so a vectorised
env shows several nets at once; ``learned_nets=(4,)`` uses net 4 only. The scene hands each env's
net to the simulator with its slices (``Slices.net_index``), so every simulator is called the same
way, ``simulator.simulate(slices)``.
Histogram matching: the LUT that maps the envs' CT onto each net's training CT is fitted once,
at construction, on CT slices at fixed pseudo-random probe poses over every patient's lower back
(``matching_sample``), so images are deterministic per pose and independent of the batch.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
import torch

#: Ultrasound simulators of an env: the model-based ultrasound models or the learned nets.
SimulatorName = Literal["physical", "sonogym", "learned"]
SIMULATORS: tuple[str, ...] = get_args(SimulatorName)
DEFAULT_LEARNED_NETS = (0, 1, 2, 3, 4)


def check_simulator(name: str, learned_nets, learned_precision: str = "float32") -> None:
    if name not in SIMULATORS:
        raise ValueError(f"simulator {name!r} is not one of {SIMULATORS}")
    from sonogym.ultrasound.learned.inference import AUTO, PRECISIONS

    if learned_precision not in (AUTO, *PRECISIONS):
        raise ValueError(
            f"learned_precision must be one of {(AUTO, *PRECISIONS)}, got {learned_precision!r}"
        )
    if name == "learned":
        from sonogym.ultrasound.learned.shipped import resolve_nets

        resolve_nets(learned_nets)  # clear errors now, not at the first image


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


def build_simulator(
    name: str,
    patients,
    device,
    learned_nets=DEFAULT_LEARNED_NETS,
    model=None,
    learned_precision: str = "float32",
):
    """The simulator of an env scene. ``model``: a configured ``PhysicalModel``/``SonoGymModel``
    used instead of the ultrasound model ``name``; ``learned_precision``: the learned nets'
    working precision ("float32", "bfloat16")."""
    if name == "learned":
        from sonogym.ultrasound.learned.shipped import resolve_nets
        from sonogym.ultrasound.learned.simulator import LearnedSimulator

        sim = LearnedSimulator(
            resolve_nets(learned_nets), device=device, precision=learned_precision
        )
        sim.fit_source(matching_sample(patients, device))
        return sim
    from sonogym.ultrasound import ModelBasedSimulator

    return ModelBasedSimulator(model if model is not None else name, device=device)


class NetChoice:
    """Which learned net each env uses: ``index`` (N,) into the scene's ``learned_nets``,
    redrawn uniformly for the reset envs by ``draw`` with uniforms from the env's generator."""

    def __init__(self, num_envs: int, num_nets: int, device) -> None:
        self.num_nets = int(num_nets)
        self.index = torch.zeros(num_envs, dtype=torch.long, device=device)

    def draw(self, env_ids: torch.Tensor, u: torch.Tensor) -> None:
        """Nets for ``env_ids`` from uniforms ``u`` in [0, 1) of the same length."""
        k = (u.to(self.index.device) * self.num_nets).long().clamp_(0, self.num_nets - 1)
        self.index[env_ids] = k


def learned_nets_tuple(value) -> tuple:
    """A config's ``learned_nets`` as a tuple (one int or path -> a 1-tuple)."""
    from pathlib import Path

    if isinstance(value, (int, str, Path)):
        return (value,)
    return tuple(value)
