"""PPO's settings (``ppo``): the paper's Tab. ppo_hype and what it leaves open from the
reference. Each task's agents module (``sonogym.tasks.<task>.agents``) holds its table."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, TypeVar

from sonogym.agents.algorithms.base import check_on_policy_params

_P = TypeVar("_P", bound="PPOParams")


@dataclass(frozen=True)
class PPOParams:
    """skrl PPO settings (paper Tab. ppo_hype; what it leaves open from the reference)."""

    rollouts: int  # env steps per env between updates
    learning_epochs: int  # passes over the rollout per update
    mini_batches: int  # mini-batches per pass
    learning_rate: float  # initial, per optimiser step, adapted by KLAdaptiveLR
    value_clip: float  # clip of the predicted value's change (value units, standardised)
    discount_factor: float = 0.99  # gamma, per env step
    gae_lambda: float = 0.95
    kl_threshold: float = 0.008  # KLAdaptiveLR target KL (not early stopping)
    grad_norm_clip: float = 1.0  # max global gradient norm
    ratio_clip: float = 0.2  # clip of the probability ratio (unitless)
    value_loss_scale: float = 1.0
    entropy_loss_scale: float = 0.0  # reference
    time_limit_bootstrap: bool = True  # see sonogym.agents.algorithms.common

    def __post_init__(self) -> None:
        check_on_policy_params(self, ("rollouts", "learning_epochs", "mini_batches"))

    @classmethod
    def from_ppo(cls: type[_P], ppo: PPOParams, **settings: Any) -> _P:
        """This config with ``ppo``'s PPO settings and ``settings`` (a PPO variant on a
        task's PPO table)."""
        return cls(**{f.name: getattr(ppo, f.name) for f in dataclasses.fields(PPOParams)},
                   **settings)  # fmt: skip
