"""skrl adapter over a ``TorchVectorEnv``: tensors stay on the env's device.

skrl's agents and memories work on flat ``(N, D)`` float observations. ``SkrlEnvAdapter``
flattens our observations with a fixed, documented ``ObsLayout``; the networks un-flatten them
with the same layout:

* a Dict observation is flattened key by key in **sorted key order** (skrl's own
  ``flatten_tensorized_space`` order, so skrl's space utilities agree), each entry reshaped to
  ``(N, prod(shape))`` and cast to float32;
* optional per-key ``obs_scales`` multiply an entry before flattening (unitless factors);
* optional running standardisation (``standardize_vectors``) of the vector entries (surgery's
  pose in metres, state observations): each feature becomes (x - mean) / std over every
  observation the training rollouts produced, so millimetre differences reach the network at
  order 1 while the env's API stays in SI units. The statistics are a module
  (``RunningStandardizer``) saved in the agent's checkpoints;
* optional ``obs_downsample`` F average-pools 2-D image entries (the last two axes, e.g. the
  navigation image (1, 200, 150) -> (1, 100, 75) for F = 2) before storage, so the rollout
  memory shrinks by F^2 as well as the network's input.

Rewards come back as ``(N, 1)`` float32, ``terminated`` / ``truncated`` as ``(N, 1)`` bool.

Autoreset: our envs reset ended episodes inside ``step`` (SAME_STEP), so the adapter never
resets per env; ``reset()`` resets all envs only on its first call and afterwards returns the
latest observations (as skrl's Isaac Lab wrapper does). The true final observation of an ended
episode is ``info["final_obs"]``; ``final_observations(info, next_obs)`` returns the flat
observations with those substituted, which time-limit bootstrapping needs (the value of the
state the episode was truncated in, not of the next episode's first state).

Privileged critic (``privileged_state=True``): the adapter also serves the task's privileged
state ``info["state"]`` as skrl's *states* (``state_space``, ``state()``,
``transition_states(info)``), which only the value network reads (asymmetric actor-critic).
The policy never sees it, so a trained policy acts from the observations alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from sonogym.envs.base import TorchVectorEnv

#: Dict entries treated as images by ``obs_downsample`` (a Box observation of >= 2 dims, the
#: navigation image, is one too); the reconstruction cube is not an image.
IMAGE_KEYS = ("image",)


@dataclass(frozen=True)
class ObsLayout:
    """Where each observation entry lies in the flat vector.

    ``keys``: entry names in flattening order (sorted; ``("_",)`` for a Box observation);
    ``shapes``: per-entry shapes after downsampling (without the batch axis).
    """

    keys: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]

    @property
    def sizes(self) -> tuple[int, ...]:
        return tuple(math.prod(s) for s in self.shapes)

    @property
    def size(self) -> int:
        """Length of the flat observation vector."""
        return sum(self.sizes)

    def shape(self, key: str) -> tuple[int, ...]:
        try:
            return self.shapes[self.keys.index(key)]
        except ValueError:
            raise KeyError(f"observation has no entry {key!r}; entries: {self.keys}") from None

    def unflatten(self, flat: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, size) -> {key: (B, *shape)} (views, no copy)."""
        if flat.shape[-1] != self.size:
            raise ValueError(
                f"flat observations must have {self.size} features, got {flat.shape[-1]}"
            )
        parts = torch.split(flat, self.sizes, dim=-1)
        return {
            k: p.reshape(*flat.shape[:-1], *s)
            for k, p, s in zip(self.keys, parts, self.shapes, strict=True)
        }


def _downsampled(shape: tuple[int, ...], factor: int) -> tuple[int, ...]:
    if factor == 1 or len(shape) < 2:
        return shape
    h, w = shape[-2], shape[-1]
    if h // factor < 1 or w // factor < 1:
        raise ValueError(f"obs_downsample {factor} is too large for an image of {shape}")
    return (*shape[:-2], h // factor, w // factor)


def obs_layout(space: gym.Space, obs_downsample: int = 1) -> ObsLayout:
    """Layout of a single-env observation space (Box or Dict of Boxes)."""
    if isinstance(space, gym.spaces.Dict):
        keys = tuple(sorted(space.spaces))
        shapes = []
        for k in keys:
            s = tuple(space[k].shape)
            shapes.append(_downsampled(s, obs_downsample) if k in IMAGE_KEYS else s)
        return ObsLayout(keys, tuple(shapes))
    if isinstance(space, gym.spaces.Box):
        s = tuple(space.shape)
        return ObsLayout(("_",), (_downsampled(s, obs_downsample) if len(s) >= 2 else s,))
    raise TypeError(f"unsupported observation space {space!r}: use a Box or a Dict of Boxes")


class RunningStandardizer(nn.Module):
    """Per-feature running mean and variance; ``forward(x, update)`` returns (x - mean) / std,
    clipped to +-``clip`` std. Statistics change only when ``update`` is true (training
    rollouts), merged batch by batch (Chan et al.); before any update it is the identity."""

    def __init__(self, size: int, clip: float = 10.0, eps: float = 1e-8) -> None:
        super().__init__()
        self.clip, self.eps = float(clip), float(eps)
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("var", torch.ones(size, dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    def forward(self, x: torch.Tensor, update: bool = False) -> torch.Tensor:
        if update and x.shape[0] > 0:
            xd = x.detach().double()
            n = float(xd.shape[0])
            b_mean, b_var = xd.mean(0), xd.var(0, unbiased=False)
            total = self.count + n
            delta = b_mean - self.mean
            m2 = self.var * self.count + b_var * n + delta**2 * self.count * n / total
            self.mean.add_(delta * n / total)
            self.var.copy_(m2 / total)
            self.count.copy_(total)
        z = (x - self.mean.to(x.dtype)) / torch.sqrt(self.var.to(x.dtype) + self.eps)
        return z.clamp(-self.clip, self.clip)


class SkrlEnvAdapter:
    """A ``TorchVectorEnv`` seen as a skrl 2.x single-agent vectorized env (``Wrapper`` API).

    Args:
        env: the batched env (SAME_STEP autoreset).
        obs_downsample: integer factor F >= 1 for 2-D image entries (average pooling).
        obs_scales: per-entry multiplicative factors (unitless), e.g. ``{"path_length": 1.0}``.
        seed: seed of the first reset.
        standardize_vectors: standardise the 1-D entries with running statistics
            (``standardizer``), updated by ``step`` while ``update_stats`` is true.
        stagger_episodes: after the first reset, shorten each env's first episode to a random
            length (``TorchVectorEnv.stagger_episodes``) so that envs end at different steps.
        privileged_state: serve ``info["state"]`` as skrl's states (for the critic only).
    """

    def __init__(
        self,
        env: TorchVectorEnv,
        obs_downsample: int = 1,
        obs_scales: dict[str, float] | None = None,
        seed: int | None = None,
        standardize_vectors: bool = False,
        stagger_episodes: bool = False,
        privileged_state: bool = False,
    ) -> None:
        if int(obs_downsample) != obs_downsample or obs_downsample < 1:
            raise ValueError(f"obs_downsample must be an integer >= 1, got {obs_downsample}")
        self._env = env
        self.obs_downsample = int(obs_downsample)
        self.layout = obs_layout(env.single_observation_space, self.obs_downsample)
        self.obs_scales = dict(obs_scales or {})
        unknown = sorted(set(self.obs_scales) - set(self.layout.keys))
        if unknown:
            raise ValueError(
                f"obs_scales names unknown entries {unknown}; entries: {self.layout.keys}"
            )
        self.seed = seed
        self._observations: torch.Tensor | None = None
        self._info: dict[str, Any] = {}
        self.stagger_episodes = bool(stagger_episodes)
        self.privileged_state = bool(privileged_state)
        self._state: torch.Tensor | None = None  # info["state"] of the current observations
        self.standardizer: RunningStandardizer | None = None
        self.update_stats = False
        if standardize_vectors:
            cols, start = [], 0
            for shape, size in zip(self.layout.shapes, self.layout.sizes, strict=True):
                if len(shape) == 1:
                    cols += range(start, start + size)
                start += size
            if cols:
                self._vector_cols = torch.tensor(cols, device=env.device)
                self.standardizer = RunningStandardizer(len(cols)).to(env.device)

    # ------------------------------------------------------------------ skrl Wrapper API
    @property
    def unwrapped(self) -> TorchVectorEnv:
        return self._env

    @property
    def device(self) -> torch.device:
        return self._env.device

    @property
    def num_envs(self) -> int:
        return self._env.num_envs

    @property
    def num_agents(self) -> int:
        return 1

    @property
    def observation_space(self) -> gym.spaces.Box:
        """Flat float32 Box of ``layout.size`` features (one env)."""
        return gym.spaces.Box(-np.inf, np.inf, (self.layout.size,), np.float32)

    @property
    def state_space(self) -> gym.spaces.Box | None:
        """Box of the privileged state of one env (``privileged_state``), else None. Its size
        is read from the first reset's info (the reset the run starts from anyway)."""
        if not self.privileged_state:
            return None
        self.reset()
        return gym.spaces.Box(-np.inf, np.inf, tuple(self._state.shape[1:]), np.float32)

    @property
    def action_space(self) -> gym.spaces.Box:
        return self._env.single_action_space

    def reset(self) -> tuple[torch.Tensor, dict[str, Any]]:
        """Reset every env on the first call; later calls return the latest observations."""
        if self._observations is None:
            self.restart(update_stats=self.update_stats)
        return self._observations, self._info

    def restart(self, update_stats: bool = False) -> None:
        """Reset every env with the adapter's seed (the run's first state again), staggering
        the episodes where asked; ``update_stats``: add these observations to the statistics."""
        obs, self._info = self._env.reset(seed=self.seed)
        if self.stagger_episodes:
            self._env.stagger_episodes()
        self._observations = self.flatten(obs, update=update_stats)
        if self.privileged_state:
            self._state = self._privileged(self._info)

    def step(
        self, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """Step all envs: obs (N, D), reward (N, 1), terminated (N, 1), truncated (N, 1), info."""
        with torch.no_grad():
            obs, reward, terminated, truncated, info = self._env.step(actions)
        self._observations = self.flatten(obs, update=self.update_stats)
        self._info = info
        if self.privileged_state:  # the new episodes' first states where an episode ended
            state = self._privileged(info)
            if "_final_obs" in info:
                mask = info["_final_obs"].to(state.device).view(-1, 1)
                state = torch.where(mask, self._privileged(self._env.current_info()), state)
            self._state = state
        return (
            self._observations,
            reward.to(torch.float32).view(-1, 1),
            terminated.view(-1, 1),
            truncated.view(-1, 1),
            info,
        )

    def state(self) -> torch.Tensor | None:
        """The privileged state (N, S) of the current observations, or None."""
        return self._state

    def transition_states(self, info: dict[str, Any]) -> torch.Tensor | None:
        """The privileged state each transition of ``step`` reached (for an ended episode, its
        final state, as ``final_observations`` gives its final observation), or None."""
        return self._privileged(info) if self.privileged_state else None

    @staticmethod
    def _privileged(info: dict[str, Any]) -> torch.Tensor:
        if "state" not in info:
            raise ValueError(
                "privileged_critic needs the env's info['state']; this env's info has "
                f"{sorted(info)}: train without privileged_critic"
            )
        state = info["state"]
        return state.to(torch.float32).reshape(state.shape[0], -1).clone()

    def render(self, *args, **kwargs) -> Any:
        return self._env.render()

    def close(self) -> None:
        self._env.close()

    # ------------------------------------------------------------------ observations
    def flatten(
        self, obs: torch.Tensor | dict[str, torch.Tensor], update: bool = False
    ) -> torch.Tensor:
        """Env observations (Box tensor or Dict of tensors) -> (N, layout.size) float32,
        vector entries standardised when enabled (``update``: add these observations to the
        statistics first)."""
        return self.standardize(self.flatten_raw(obs), update)

    def flatten_raw(self, obs: torch.Tensor | dict[str, torch.Tensor]) -> torch.Tensor:
        """``flatten`` without the standardisation: downsampled, scaled, flat (N, layout.size)
        float32 (what a sample store keeps, standardised later with ``standardize``)."""
        entries = obs if isinstance(obs, dict) else {"_": obs}
        parts = []
        for key, shape in zip(self.layout.keys, self.layout.shapes, strict=True):
            x = entries[key].to(torch.float32)
            if tuple(x.shape[1:]) != shape:  # downsampled image entry
                n = x.shape[0]
                x = F.avg_pool2d(x.reshape(-1, 1, *x.shape[-2:]), self.obs_downsample)
                x = x.reshape(n, *shape)
            scale = self.obs_scales.get(key)
            if scale is not None:
                x = x * scale
            parts.append(x.reshape(x.shape[0], -1))
        return torch.cat(parts, dim=-1)

    def standardize(self, flat: torch.Tensor, update: bool = False) -> torch.Tensor:
        """``flatten_raw``'s (N, layout.size) with the vector entries standardised where
        enabled (``update``: add them to the statistics first), in place; else unchanged."""
        if self.standardizer is not None:
            cols = self._vector_cols
            flat[:, cols] = self.standardizer(flat[:, cols], update=update)
        return flat

    def final_observations(self, info: dict[str, Any], next_obs: torch.Tensor) -> torch.Tensor:
        """``next_obs`` with the true final observations of the envs whose episode just ended
        (``info["final_obs"]``, SAME_STEP autoreset) substituted: the s_{t+1} of each
        transition, for bootstrapping."""
        if "final_obs" not in info:
            return next_obs
        mask = info["_final_obs"].to(next_obs.device)
        return torch.where(mask.view(-1, 1), self.flatten(info["final_obs"]), next_obs)
