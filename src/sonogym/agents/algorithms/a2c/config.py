"""A2C's settings (``a2c``): the paper's Tab. a2c_hype. Each task's agents module
(``sonogym.tasks.<task>.agents``) holds its table."""

from __future__ import annotations

from dataclasses import dataclass

from sonogym.agents.algorithms.base import check_on_policy_params


@dataclass(frozen=True)
class A2CParams:
    """skrl A2C settings (paper Tab. a2c_hype; A2C has no epochs: the table's
    ``learning_epochs`` is not an A2C setting and is not used)."""

    rollouts: int  # env steps per env between updates
    mini_batches: int  # mini-batches per update
    learning_rate: float = 1e-4  # initial, adapted by KLAdaptiveLR (reference)
    discount_factor: float = 0.99  # gamma, per env step
    gae_lambda: float = 0.95
    kl_threshold: float = 0.008  # KLAdaptiveLR target KL
    grad_norm_clip: float = 1.0  # max global gradient norm
    entropy_loss_scale: float = 0.0
    time_limit_bootstrap: bool = True  # see sonogym.agents.algorithms.common

    def __post_init__(self) -> None:
        check_on_policy_params(self, ("rollouts", "mini_batches"))
