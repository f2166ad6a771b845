"""A2C (``a2c``): its config (``A2CParams``) and its ``AlgorithmSpec``."""

from sonogym.agents.algorithms.a2c.algorithm import A2C_ALGORITHM
from sonogym.agents.algorithms.a2c.config import A2CParams

__all__ = ["A2C_ALGORITHM", "A2CParams"]
