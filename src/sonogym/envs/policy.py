"""The one interface every controller of a batched env implements, and the simple ones.

A ``Policy`` maps a batch of observations (and the env's ``info``) to a batch of actions. It
may keep per-env state (an observation history, a queue of predicted actions, a temporal
ensemble): ``reset(env_mask)`` clears that state for the envs whose episode starts anew. The
rollout loop (``sonogym.envs.rollout``) calls ``reset()`` once before the first step and
``reset(mask)`` for the envs an autoreset restarted, so stateful policies (ACT's action chunks,
Diffusion Policy's observation history) never mix two episodes.

Implemented by the task experts and the reconstruction heuristic (``ExpertPolicy``, from the
task registry), ``RandomPolicy``, trained RL checkpoints (``sonogym.agents.checkpoint``) and
the imitation-learning policies (``sonogym.imitation``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch


@runtime_checkable
class Policy(Protocol):
    """A batched controller: ``act(obs, info) -> (N, A)`` actions on the env's device."""

    def reset(self, env_mask: torch.Tensor | None = None) -> None:
        """Forget per-env state for the envs in ``env_mask`` ((N,) bool; None: every env)."""

    def act(self, obs: Any, info: dict[str, Any]) -> torch.Tensor:
        """Actions (N, A) for observations ``obs`` (the env's batch) and its ``info``."""


class StatelessPolicy:
    """Base of policies without per-env state: ``reset`` does nothing."""

    def reset(self, env_mask: torch.Tensor | None = None) -> None:
        return None

    def act(self, obs: Any, info: dict[str, Any]) -> torch.Tensor:
        raise NotImplementedError


class ExpertPolicy(StatelessPolicy):
    """A task's privileged expert (or heuristic) as a ``Policy``: ``fn(env, info)`` reads the
    true state from ``info`` (and, for the open-loop raster, the env's step counters)."""

    def __init__(self, env, fn: Callable[[Any, dict[str, Any]], torch.Tensor]) -> None:
        self.env = env
        self.fn = fn

    def act(self, obs: Any, info: dict[str, Any]) -> torch.Tensor:
        return self.fn(self.env, info)


class RandomPolicy(StatelessPolicy):
    """Actions uniform in the env's single action box, from a seeded generator."""

    def __init__(self, env, seed: int = 0) -> None:
        space = env.single_action_space
        self.device = env.device
        self.num_envs = env.num_envs
        self.low = torch.as_tensor(space.low, dtype=torch.float32, device=self.device)
        self.high = torch.as_tensor(space.high, dtype=torch.float32, device=self.device)
        self.gen = torch.Generator(device="cpu").manual_seed(int(seed))

    def act(self, obs: Any, info: dict[str, Any]) -> torch.Tensor:
        u = torch.rand(self.num_envs, *self.low.shape, generator=self.gen).to(self.device)
        return self.low + (self.high - self.low) * u
