"""``a2c``: skrl's A2C on the shared Gaussian policy / value network (on reconstruction the
paper's submodular A2C)."""

from __future__ import annotations

from sonogym.agents.algorithms.a2c.config import A2CParams
from sonogym.agents.algorithms.base import AgentSetup, AlgorithmSpec


def build(setup: AgentSetup):
    from skrl.agents.torch.a2c import A2C, A2C_CFG

    from sonogym.agents.algorithms.common import make_agent, on_policy_settings

    return make_agent(A2C, A2C_CFG(**on_policy_settings(setup)), setup)


A2C_ALGORITHM = AlgorithmSpec(name="a2c", label="A2C", config_cls=A2CParams, build=build)
