"""The batched environment core shared by every task.

``TorchVectorEnv`` is a Gymnasium ``VectorEnv`` whose observations, rewards and flags are
batch-first torch tensors on the env's device. Tasks implement small hooks (IsaacLab's direct-env
habit) and keep their reward math in pure functions:

* ``_reset_idx(env_ids)``: sample the initial state of these envs (partial reset);
* ``_apply_action(actions)``: advance the simulation with validated (N, A) actions;
* ``_get_rewards()``, ``_get_terminated()``: for the transition just made (no one-step lag);
* ``_get_observations(env_ids)``: observations of some envs;
* ``_get_info()``: privileged state, cost, etc. for all envs;
* ``_episode_metrics(env_ids)``: the task's metrics of episodes that just ended.

Autoreset mode is SAME_STEP: an env whose episode ends is reset inside the same ``step``; the
returned observation is the new episode's first, and the true final observation and the
episode's metrics are in ``info["final_obs"]`` / ``info["final_info"]`` with masks
``info["_final_obs"]`` / ``info["_final_info"]`` (Gymnasium's convention, as tensors).

``info`` describes the transition the step made (its cost, the state it reached). For an env
reset inside the step that is the finished episode's last transition; the new episode's state
appears in the next step's ``info`` (state-based experts act once on the old state, a no-op
near their goal). ``reset()`` returns the new state in its ``info``.
"""

from __future__ import annotations

import dataclasses
import math
from numbers import Integral
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from sonogym.checks import expect_all


def make_config(cls: type, kwargs: dict[str, Any]):
    """Build a frozen config dataclass from keyword arguments, naming unknown keys."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(kwargs) - names)
    if unknown:
        raise TypeError(
            f"unknown {cls.__name__} option(s) {unknown}; valid options are {sorted(names)}"
        )
    return cls(**kwargs)


def check_number_fields(cfg: Any) -> None:
    """Refuse what no numeric setting can mean, by the field's annotation: a ``float`` field
    (alone, optional or in a tuple of floats) must be a finite number (NaN, inf, or 1e309,
    which reads as inf, are refused); an ``int`` field an integer, where an integral float
    such as 2.0 is taken as 2 and 2.5 is refused (never truncated); a bool is no number.
    Call first in a frozen config dataclass's ``__post_init__``."""
    name = type(cfg).__name__
    for f in dataclasses.fields(cfg):
        kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
        v = getattr(cfg, f.name)
        if kind == "int":
            object.__setattr__(cfg, f.name, _integer(f"{name}.{f.name}", v))
        elif kind == "float" or (kind == "float | None" and v is not None):
            _finite(f"{name}.{f.name}", v)
        elif kind.startswith("tuple[float") and isinstance(v, tuple | list):
            for i, x in enumerate(v):
                _finite(f"{name}.{f.name}[{i}]", x)
        elif kind.startswith("dict[str, float]") and isinstance(v, dict):
            for k, x in v.items():
                _finite(f"{name}.{f.name}[{k!r}]", x)


def _finite(what: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
        raise ValueError(f"{what} must be a finite number, got {v!r}; give a number in its unit")


def _integer(what: str, v: Any) -> int:
    if isinstance(v, float) and v.is_integer():
        return int(v)
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{what} must be an integer, got {v!r}; give a whole number (it is "
                         "never rounded)")  # fmt: skip
    return v


class TorchVectorEnv(VectorEnv):
    """Batched env over torch tensors. Subclasses set the spaces and implement the hooks."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"]}

    def __init__(self, num_envs: int, device: str | torch.device, episode_length: int) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, Integral) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if isinstance(episode_length, bool) or not isinstance(episode_length, Integral):
            raise ValueError(f"episode_length must be an integer (steps), got {episode_length!r}")
        self.num_envs = int(num_envs)
        self.device = torch.device(device)
        self.episode_length = int(episode_length)
        self.render_mode = "rgb_array"
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long, device=self.device)
        # steps after which each env's current episode is truncated (stagger_episodes shortens it)
        self.time_limit = torch.full_like(self.episode_length_buf, self.episode_length)
        self.episode_return = torch.zeros(self.num_envs, dtype=torch.float32, device=self.device)
        self._gen = torch.Generator(device="cpu")
        self._gen.manual_seed(0)
        self._needs_reset = True

    def _set_spaces(self, single_obs: gym.Space, single_action: gym.spaces.Box) -> None:
        self.single_observation_space = single_obs
        self.single_action_space = single_action
        self.observation_space = batch_space(single_obs, self.num_envs)
        self.action_space = batch_space(single_action, self.num_envs)

    # ------------------------------------------------------------------ random draws
    def rand(self, *shape: int) -> torch.Tensor:
        """Uniform [0, 1) draws from the env's seeded generator, on the env's device."""
        return torch.rand(*shape, generator=self._gen, dtype=torch.float64).to(self.device)

    def uniform(self, low, high, *shape: int) -> torch.Tensor:
        return low + (high - low) * self.rand(*shape)

    # ------------------------------------------------------------------ API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset all envs, or those in ``options["reset_mask"]`` (bool, shape (num_envs,))."""
        if seed is not None:
            self._gen.manual_seed(int(seed))
        mask = (options or {}).get("reset_mask")
        if mask is None:
            ids = torch.arange(self.num_envs, device=self.device)
        else:
            mask = torch.as_tensor(mask, dtype=torch.bool, device=self.device)
            if mask.shape != (self.num_envs,):
                raise ValueError(
                    f"reset_mask must have shape ({self.num_envs},), got {tuple(mask.shape)}"
                )
            ids = torch.nonzero(mask).flatten()
            if self._needs_reset and len(ids) < self.num_envs:
                raise RuntimeError("the first reset must reset every env (no reset_mask)")
        self._reset_envs(ids)
        self._needs_reset = False
        return self._get_observations(None), self._get_info()

    def step(self, actions) -> tuple[Any, torch.Tensor, torch.Tensor, torch.Tensor, dict]:
        if self._needs_reset:
            raise RuntimeError("call reset() before step()")
        actions = self._validate_actions(actions)
        self._apply_action(actions)
        self.episode_length_buf += 1
        reward = self._get_rewards().to(torch.float32)
        self.episode_return += reward
        terminated = self._get_terminated()
        truncated = (self.episode_length_buf >= self.time_limit) & ~terminated
        info = self._get_info()
        obs = self._get_observations(None)
        done = terminated | truncated
        if bool(done.any()):
            ids = torch.nonzero(done).flatten()
            info["final_obs"] = _clone(obs)
            info["_final_obs"] = done.clone()
            info["final_info"] = self._episode_metrics(ids)
            info["final_info"]["return"] = self.episode_return[ids].clone()
            info["final_info"]["env_ids"] = ids
            info["_final_info"] = done.clone()
            self._reset_envs(ids)
            _scatter(obs, ids, self._get_observations(ids))
        return obs, reward, terminated, truncated, info

    def stagger_episodes(self) -> None:
        """Truncate each env's current episode after a uniform draw of 1 ... episode_length
        steps (the env's seeded generator); later episodes have the full length, so from then
        on envs end at different steps. For training: with every env in the same phase, each
        short rollout shows the learner one phase of the task only (all approach, or all
        inside the corridor), and an update fitted to one phase can wreck the others, which
        no sample constrains (IsaacLab randomises initial episode lengths the same way).
        Call after ``reset()``; evaluation keeps whole episodes."""
        if self._needs_reset:
            raise RuntimeError("call reset() before stagger_episodes()")
        draw = (self.rand(self.num_envs) * self.episode_length).long() + 1
        self.time_limit.copy_(draw.clamp(max=self.episode_length).to(self.device))

    def _reset_envs(self, ids: torch.Tensor) -> None:
        self.episode_length_buf[ids] = 0
        self.time_limit[ids] = self.episode_length
        self.episode_return[ids] = 0
        self._reset_idx(ids)

    def _validate_actions(self, actions) -> torch.Tensor:
        a = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        want = (self.num_envs, *self.single_action_space.shape)
        if a.shape != want:
            raise ValueError(
                f"actions must have shape {want} (num_envs, action_dim), got {tuple(a.shape)}"
            )
        expect_all(
            torch.isfinite(a),
            lambda: (
                "actions contain NaN or inf (envs "
                f"{torch.nonzero(~torch.isfinite(a).all(-1)).flatten().tolist()[:10]})"
            ),
        )
        return a

    def current_info(self) -> dict[str, Any]:
        """The info of every env's current state (after an autoreset: the new episodes' start
        states, which ``step``'s own info, describing the finished transition, does not hold)."""
        return self._get_info()

    def current_metrics(self, env_ids: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The task's episode metrics of the envs' current states (None: every env), as
        ``final_info`` would report them if their episodes ended now (without ``return``)."""
        ids = torch.arange(self.num_envs, device=self.device) if env_ids is None else env_ids
        return self._episode_metrics(ids)

    def render(self) -> np.ndarray:
        """RGB frame (uint8, H x W x 3) of env 0."""
        return self._render_frame()

    def close(self, **kwargs: Any) -> None:
        pass

    # ------------------------------------------------------------------ hooks
    def _reset_idx(self, env_ids: torch.Tensor) -> None:
        raise NotImplementedError

    def _apply_action(self, actions: torch.Tensor) -> None:
        raise NotImplementedError

    def _get_rewards(self) -> torch.Tensor:
        raise NotImplementedError

    def _get_terminated(self) -> torch.Tensor:
        return torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)

    def _get_observations(self, env_ids: torch.Tensor | None):
        raise NotImplementedError

    def _get_info(self) -> dict[str, Any]:
        return {}

    def _episode_metrics(self, env_ids: torch.Tensor) -> dict[str, torch.Tensor]:
        return {}

    def _render_frame(self) -> np.ndarray:
        raise NotImplementedError


def _clone(obs):
    if isinstance(obs, dict):
        return {k: v.clone() for k, v in obs.items()}
    return obs.clone()


def _scatter(obs, ids: torch.Tensor, new) -> None:
    if isinstance(obs, dict):
        for k in obs:
            obs[k][ids] = new[k]
    else:
        obs[ids] = new


class SingleEnv(gym.Env):
    """One env of a ``TorchVectorEnv`` as a plain ``gymnasium.Env`` with NumPy I/O (what
    ``gymnasium.make`` returns). The batched env is the fast path; this is for tools and checks."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, vector_cls: type[TorchVectorEnv], render_mode: str | None = None, **kwargs):
        self._env = vector_cls(num_envs=1, **kwargs)
        self.observation_space = self._env.single_observation_space
        self.action_space = self._env.single_action_space
        self.render_mode = render_mode
        self.spec_kwargs = kwargs

    @property
    def unwrapped_vector(self) -> TorchVectorEnv:
        return self._env

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs, info = self._env.reset(seed=seed)
        return _to_numpy(obs), _info_numpy(info)

    def step(self, action):
        a = np.asarray(action, dtype=np.float32)[None]
        obs, rew, term, trunc, info = self._env.step(a)
        if "final_obs" in info:
            obs = info.pop("final_obs")
        return (
            _to_numpy(obs),
            float(rew[0]),
            bool(term[0]),
            bool(trunc[0]),
            _info_numpy(info),
        )

    def render(self):
        return self._env.render()


def _to_numpy(obs):
    if isinstance(obs, dict):
        return {k: v[0].cpu().numpy() for k, v in obs.items()}
    return obs[0].cpu().numpy()


def _info_numpy(info: dict) -> dict:
    out = {}
    for k, v in info.items():
        if isinstance(v, torch.Tensor):
            out[k] = v[0].cpu().numpy() if v.ndim and v.shape[0] == 1 else v.cpu().numpy()
        elif isinstance(v, dict):
            out[k] = _info_numpy(v)
        else:
            out[k] = v
    return out
