"""Trained IL policies as env ``Policy`` objects (``sonogym.envs.policy.Policy`` protocol).

``ILPolicy.act(obs, info)`` turns the env's batch into the dataset's features with the task's
``obs_to_features(obs, info) -> {key: tensor}`` (keys as in the dataset:
``observation.images.<name>`` float (N, C, H, W) in [0, 1], ``observation.state`` (N, D)),
and returns (N, A) actions in the dataset's action units on the features' device. Per-env
state, batched over envs, as the model's config asks (``ILConfig``):

* ``temporal_ensemble_coeff`` set (ACT's default): a new chunk every step, executed through
  the temporal ensemble (``buffers.TemporalEnsembler``); unset: chunks of ``n_action_steps``
  actions from a per-env queue, a new chunk only for the envs whose queue ran out.
* ``observation_steps`` n (Diffusion Policy: ``n_obs_steps``): the last n observations per env
  (a reset env's first observation fills its history); None (ACT): the current one.

``reset(env_mask)`` clears that state for the masked envs only (all envs for None).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from sonogym.imitation.buffers import ActionQueue, ObsHistory, TemporalEnsembler
from sonogym.imitation.policies.base import ILModel
from sonogym.imitation.processor import STATE_KEY
from sonogym.imitation.run import load_model

ObsToFeatures = Callable[[Any, dict[str, Any]], dict[str, torch.Tensor]]


class ILPolicy:
    """A trained IL model acting in a batched env (see the module doc).

    Args:
        model: an ``ILModel`` (ACT, Diffusion Policy, ...; eval mode is set here).
        obs_to_features: the task's observation -> dataset-feature conversion.
        seed: seed of the model's sampling noise (Diffusion Policy's).
    """

    def __init__(self, model: ILModel, obs_to_features: ObsToFeatures, seed: int = 0):
        if not isinstance(model, ILModel):
            raise TypeError(f"expected an imitation-learning model (ILModel), got "
                            f"{type(model).__name__}")  # fmt: skip
        self.model = model.eval()
        self.obs_to_features = obs_to_features
        self.config = model.config
        self.features = model.features
        self.device = next(model.parameters()).device
        self.generator = torch.Generator(device=self.device).manual_seed(int(seed))
        self.num_envs: int | None = None
        self.history_steps = self.config.observation_steps
        self.ensemble = self.config.temporal_ensemble_coeff is not None
        self._keys = (*self.features.image_keys, *((STATE_KEY,) if self.features.state_dim else ()))

    def _allocate(self, n: int) -> None:
        a = self.features.action_dim
        self.num_envs = n
        if self.ensemble:
            self.ensembler = TemporalEnsembler(
                self.config.temporal_ensemble_coeff, self.config.chunk_length, n, a, self.device
            )
        else:
            self.queue = ActionQueue(self.config.n_action_steps, n, a, self.device)
        if self.history_steps is not None:
            self.history = {k: ObsHistory(self.history_steps) for k in self._keys}

    def reset(self, env_mask: torch.Tensor | None = None) -> None:
        """Forget the per-env state of the envs in ``env_mask`` ((N,) bool; None: all)."""
        if self.num_envs is None:
            return
        if env_mask is not None:
            env_mask = torch.as_tensor(env_mask, device=self.device).bool()
        if self.ensemble:
            self.ensembler.reset(env_mask)
        else:
            self.queue.reset(env_mask)
        if self.history_steps is not None:
            for h in self.history.values():
                h.reset(env_mask)

    def _features(self, obs: Any, info: dict[str, Any]) -> tuple[dict[str, torch.Tensor], Any]:
        feats = self.obs_to_features(obs, info)
        missing = [k for k in self._keys if k not in feats]
        if missing:
            raise KeyError(
                f"obs_to_features gave no {missing}; the policy needs {list(self._keys)}"
            )
        out_device = feats[self._keys[0]].device
        n = feats[self._keys[0]].shape[0]
        out = {}
        resized = self.config.image_size is not None
        for k, shape in zip(self.features.image_keys, self.features.image_shapes, strict=True):
            x = feats[k]
            ok = (
                x.ndim == 4
                and x.shape[0] == n
                and (x.shape[1] == shape[0] if resized else tuple(x.shape[1:]) == shape)
            )
            if not ok:
                raise ValueError(f"{k}: expected (N, C, H, W) = (N, {shape}), got {tuple(x.shape)}")
            out[k] = x.to(self.device, torch.float32)
        if self.features.state_dim:
            s = feats[STATE_KEY]
            if tuple(s.shape) != (n, self.features.state_dim):
                raise ValueError(
                    f"{STATE_KEY}: expected ({n}, {self.features.state_dim}), got {tuple(s.shape)}"
                )
            out[STATE_KEY] = s.to(self.device, torch.float32)
        return out, out_device

    @torch.no_grad()
    def act(self, obs: Any, info: dict[str, Any]) -> torch.Tensor:
        """Actions (N, A) in dataset action units for the env batch ``obs``."""
        feats, out_device = self._features(obs, info)
        n = next(iter(feats.values())).shape[0]
        if self.num_envs != n:
            self._allocate(n)
        if self.history_steps is not None:
            feats = {k: self.history[k].push(v) for k, v in feats.items()}
        if self.ensemble:
            action = self.ensembler.update(self.model.predict_chunk(feats, self.generator))
        else:
            need = self.queue.empty()
            if bool(need.any()):
                idx = need.nonzero().squeeze(1)
                sub = {k: v[idx] for k, v in feats.items()}
                self.queue.fill(idx, self.model.predict_chunk(sub, self.generator))
            action = self.queue.pop()
        return action.to(out_device)


def load_il_policy(
    run_dir: str | Path,
    obs_to_features: ObsToFeatures,
    device: str | torch.device = "cpu",
    checkpoint: str | Path | None = None,
    seed: int = 0,
    **inference_overrides,
) -> ILPolicy:
    """``ILPolicy`` from a ``train_il`` run folder (newest checkpoint unless ``checkpoint``).

    ``inference_overrides``: inference-only config changes, e.g. ``temporal_ensemble_coeff=None,
    n_action_steps=100`` (ACT chunk execution) or ``scheduler="ddim", num_inference_steps=10``.
    """
    model, _ = load_model(run_dir, device, checkpoint, **inference_overrides)
    return ILPolicy(model, obs_to_features, seed=seed)
