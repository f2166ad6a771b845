"""PPO (``ppo``): its config (``PPOParams``) and its ``AlgorithmSpec``."""

from sonogym.agents.algorithms.ppo.algorithm import PPO_ALGORITHM
from sonogym.agents.algorithms.ppo.config import PPOParams

__all__ = ["PPO_ALGORITHM", "PPOParams"]
