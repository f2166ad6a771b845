"""``ppo-lag``: PPO with a cost value network and a PID Lagrange multiplier (``agent``)."""

from __future__ import annotations

from typing import Any

from sonogym.agents.algorithms.base import AgentSetup, AlgorithmSpec, ModelSetup
from sonogym.agents.algorithms.ppo_lag.config import PPOLagrangianParams


def build(setup: AgentSetup):
    from sonogym.agents.algorithms.common import make_agent, ppo_settings
    from sonogym.agents.algorithms.ppo_lag.agent import PPO_LAG_CFG, PPOLagrangian

    p = setup.config
    cfg = PPO_LAG_CFG(**ppo_settings(setup), cost_learning_rate=p.cost_learning_rate,
                      cost_limit=p.cost_limit, pid_gains=p.pid_gains)  # fmt: skip
    return make_agent(PPOLagrangian, cfg, setup)


def models(setup: ModelSetup) -> dict[str, Any]:
    from sonogym.agents.algorithms.ppo_lag.agent import CostValue

    value = CostValue(setup.task, setup.layout, setup.action_space, setup.device, setup.net)
    return {"cost_value": value}


PPO_LAG_ALGORITHM = AlgorithmSpec(
    name="ppo-lag",
    label="PPO-Lag",
    config_cls=PPOLagrangianParams,
    build=build,
    models=models,
)
