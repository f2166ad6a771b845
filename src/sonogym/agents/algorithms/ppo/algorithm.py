"""``ppo``: skrl's PPO on the shared Gaussian policy / value network (on reconstruction the
paper's submodular PPO: the env's reward is the objective's marginal gain)."""

from __future__ import annotations

from sonogym.agents.algorithms.base import AgentSetup, AlgorithmSpec
from sonogym.agents.algorithms.ppo.config import PPOParams


def build(setup: AgentSetup):
    from skrl.agents.torch.ppo import PPO, PPO_CFG

    from sonogym.agents.algorithms.common import make_agent, ppo_settings

    return make_agent(PPO, PPO_CFG(**ppo_settings(setup)), setup)


PPO_ALGORITHM = AlgorithmSpec(name="ppo", label="PPO", config_cls=PPOParams, build=build)
