"""The envs' side of the ultrasound simulator: which learned net each env uses.

The simulator itself comes from the registry (``sonogym.ultrasound.registry``) by the config's
``simulator`` name; every simulator is called the same way, ``simulator.simulate(slices)``. A
simulator that ``draws_net`` (the learned one) images each env with one net of
``learned_nets`` (ints: shipped nets by index, strings: paths to ``generator.pt`` files): like
the paper, each env draws one net of the set uniformly at every episode reset, from the env's
seeded generator (``NetChoice``), so a vectorised env shows several nets at once;
``learned_nets=(4,)`` uses net 4 only. The scene hands each env's net to the simulator with its
slices (``Slices.net_index``).
"""

from __future__ import annotations

import torch


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
