"""PPO-Lagrangian (``ppo-lag``): its config (``PPOLagrangianParams``) and its
``AlgorithmSpec``; the skrl agent and cost value are in ``agent``."""

from sonogym.agents.algorithms.ppo_lag.algorithm import PPO_LAG_ALGORITHM
from sonogym.agents.algorithms.ppo_lag.config import PPOLagrangianParams

__all__ = ["PPO_LAG_ALGORITHM", "PPOLagrangianParams"]
