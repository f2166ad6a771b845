"""PPO + safety filter (``ppo-sf``): its config (``PPOSafetyFilterParams``) and its
``AlgorithmSpec``; the skrl agent, cost critic and filter are in ``agent``."""

from sonogym.agents.algorithms.ppo_sf.algorithm import PPO_SF_ALGORITHM
from sonogym.agents.algorithms.ppo_sf.config import PPOSafetyFilterParams

__all__ = ["PPO_SF_ALGORITHM", "PPOSafetyFilterParams"]
