"""What a policy sees of a dataset (``PolicyFeatures``) and its normalisation (``Normalizer``).

LeRobot splits a policy into config, model and processor; the processor normalises inputs and
targets with the dataset's ``stats.json`` and unnormalises predicted actions. Here the
``Normalizer`` is a module inside each policy, so its statistics travel in the checkpoint's
state_dict. Modes (LeRobot 0.4's formulas, eps = 1e-8):

* ``mean_std``: (x - mean) / (std + eps); inverse x (std + eps) + mean.
* ``min_max``:  2 (x - min) / d - 1 with d = max - min (eps where max == min), to [-1, 1];
  inverse (x + 1) d / 2 + min.
* ``identity``: unchanged.

Feature types: images (``observation.images.*``, dtype "image": per-channel stats (C, 1, 1)),
the state (``observation.state``) and the action (``action``), each with its own mode.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from sonogym.imitation.lerobot_format import is_image

MODES = ("mean_std", "min_max", "identity")
STATE_KEY = "observation.state"
ACTION_KEY = "action"
EPS = 1e-8


@dataclass(frozen=True)
class PolicyFeatures:
    """The dataset features a policy uses.

    image_keys: camera keys in a fixed order (``observation.images.<name>``).
    image_shapes: (C, H, W) per camera, in pixels, as stored.
    state_dim: length of ``observation.state`` (0: the dataset has none).
    action_dim: length of ``action``.
    """

    image_keys: tuple[str, ...]
    image_shapes: tuple[tuple[int, int, int], ...]
    state_dim: int
    action_dim: int

    @classmethod
    def from_info(cls, info_features: dict[str, dict[str, Any]]) -> PolicyFeatures:
        """From ``info.json``'s features: every image feature, ``observation.state`` if there
        is one, and ``action`` (required)."""
        if ACTION_KEY not in info_features:
            raise KeyError(f"the dataset has no {ACTION_KEY!r} feature: nothing to imitate")
        keys = tuple(k for k, ft in info_features.items() if is_image(ft))
        shapes = tuple(
            (
                int(info_features[k]["shape"][2]),
                int(info_features[k]["shape"][0]),
                int(info_features[k]["shape"][1]),
            )
            for k in keys
        )
        state = info_features.get(STATE_KEY)
        return cls(
            image_keys=keys,
            image_shapes=shapes,
            state_dim=int(state["shape"][0]) if state else 0,
            action_dim=int(info_features[ACTION_KEY]["shape"][0]),
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "image_keys": list(self.image_keys),
            "image_shapes": [list(s) for s in self.image_shapes],
            "state_dim": self.state_dim,
            "action_dim": self.action_dim,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PolicyFeatures:
        return cls(
            tuple(d["image_keys"]),
            tuple(tuple(int(v) for v in s) for s in d["image_shapes"]),
            int(d["state_dim"]),
            int(d["action_dim"]),
        )

    @property
    def keys(self) -> tuple[str, ...]:
        """Every input and output key (images, state if any, action)."""
        return (*self.image_keys, *((STATE_KEY,) if self.state_dim else ()), ACTION_KEY)


def norm_modes(features: PolicyFeatures, visual: str, state: str, action: str) -> dict[str, str]:
    """Mode per key from the per-type modes of a policy config."""
    for m in (visual, state, action):
        if m not in MODES:
            raise ValueError(f"normalisation mode {m!r} unknown; use one of {MODES}")
    modes = {k: visual for k in features.image_keys}
    if features.state_dim:
        modes[STATE_KEY] = state
    modes[ACTION_KEY] = action
    return modes


class Normalizer(nn.Module):
    """Normalise / unnormalise features with fixed dataset statistics (see the module doc).

    Args:
        stats: ``{key: {"mean", "std", "min", "max": tensor}}`` (``load_stats`` output); image
            stats (C, 1, 1), vector stats (D,).
        modes: ``{key: mode}``; keys absent here pass unchanged.
    """

    def __init__(self, stats: dict[str, dict[str, torch.Tensor]], modes: dict[str, str]) -> None:
        super().__init__()
        self.modes = dict(modes)
        self._names: dict[str, str] = {}
        for i, (key, mode) in enumerate(self.modes.items()):
            if mode not in MODES:
                raise ValueError(f"{key}: normalisation mode {mode!r} unknown; use one of {MODES}")
            if mode == "identity":
                continue
            if key not in stats:
                raise KeyError(f"stats.json has no entry for {key!r}; cannot normalise it")
            s = stats[key]
            if mode == "mean_std":
                scale, shift = s["std"].float() + EPS, s["mean"].float()
            else:
                d = s["max"].float() - s["min"].float()
                d = torch.where(d == 0, torch.full_like(d, EPS), d)
                # x_n = 2 (x - min) / d - 1 = (x - (min + d / 2)) / (d / 2)
                scale, shift = d / 2, s["min"].float() + d / 2
            name = f"f{i}"
            self._names[key] = name
            self.register_buffer(f"{name}_scale", scale.clone())
            self.register_buffer(f"{name}_shift", shift.clone())

    def _params(self, key: str) -> tuple[torch.Tensor, torch.Tensor] | None:
        name = self._names.get(key)
        if name is None:
            return None
        return getattr(self, f"{name}_scale"), getattr(self, f"{name}_shift")

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        p = self._params(key)
        return x if p is None else (x - p[1]) / p[0]

    def unnormalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        p = self._params(key)
        return x if p is None else x * p[0] + p[1]

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """A copy of ``batch`` with every known key normalised (other keys unchanged)."""
        return {k: self.normalize(k, v) if k in self.modes else v for k, v in batch.items()}


def stats_subset(
    stats: dict[str, dict[str, torch.Tensor]], keys: tuple[str, ...]
) -> dict[str, dict[str, list]]:
    """The stats a run used, JSON-ready (for its config.json)."""
    names = ("mean", "std", "min", "max")
    return {
        k: {s: stats[k][s].tolist() for s in names if s in stats[k]} for k in keys if k in stats
    }
