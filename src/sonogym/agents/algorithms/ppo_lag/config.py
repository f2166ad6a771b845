"""PPO-Lagrangian's settings (``ppo-lag``): a task's PPO table plus the constraint's and the
cost value's (see ``sonogym.agents.algorithms.ppo_lag.agent``)."""

from __future__ import annotations

from dataclasses import dataclass

from sonogym.agents.algorithms.ppo.config import PPOParams


@dataclass(frozen=True)
class PPOLagrangianParams(PPOParams):
    """PPO's settings plus the Lagrangian's; ``from_ppo(table)`` puts them on a task's PPO
    table."""

    cost_learning_rate: float = 1e-4  # Adam lr of the cost value, per optimiser step (reference)
    cost_limit: float = 5.0  # limit on the mean discounted cost return (cost units)
    pid_gains: tuple[float, float, float] = (0.05, 0.0005, 0.1)  # Kp, Ki, Kd (reference)
