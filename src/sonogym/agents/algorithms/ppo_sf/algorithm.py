"""``ppo-sf``: PPO plus a cost critic trained beside it, whose safety filter acts at test time
(``agent``). Evaluation runs the policy through its filter ("policy") and without it
("unfiltered"), and may override the filter's mode and threshold (``safety_filter``)."""

from __future__ import annotations

from typing import Any

from sonogym.agents.algorithms.base import (
    Acting,
    ActingSettings,
    ActingSetup,
    AgentSetup,
    AlgorithmSpec,
    ModelSetup,
)
from sonogym.agents.algorithms.ppo_sf.config import PPOSafetyFilterParams, resolve_filter

#: a run's policy without its safety filter (the PPO it trained: the filter acts only at test
#: time), evaluated beside the filtered one by default
UNFILTERED = "unfiltered"


def build(setup: AgentSetup):
    from sonogym.agents.algorithms.common import make_agent, ppo_settings
    from sonogym.agents.algorithms.ppo_sf.agent import PPO_SF_CFG, PPOSafetyFilter

    p = setup.config
    cfg = PPO_SF_CFG(**ppo_settings(setup), cost_learning_rate=p.cost_learning_rate,
                     cost_threshold=p.cost_threshold)  # fmt: skip
    return make_agent(PPOSafetyFilter, cfg, setup)


def models(setup: ModelSetup) -> dict[str, Any]:
    from sonogym.agents.algorithms.ppo_sf.agent import CostCritic

    critic = CostCritic(setup.task, setup.layout, setup.action_space, setup.device, setup.net)
    return {"cost_critic": critic}


def acting_policy(setup: ActingSetup):
    """The run's policy through its safety filter ("policy"), or as PPO trained it
    ("unfiltered")."""
    if setup.controller == UNFILTERED:
        return setup.policy
    from sonogym.agents.algorithms.ppo_sf.agent import SafetyFilteredPolicy, load_cost_critic

    critic, _, _ = load_cost_critic(setup.run, setup.checkpoint, setup.device)
    settings = setup.settings or resolve_filter(setup.config, {})
    return SafetyFilteredPolicy(setup.policy.model, setup.policy.adapter, critic,
                                settings["threshold"], settings["mode"])  # fmt: skip


PPO_SF_ALGORITHM = AlgorithmSpec(
    name="ppo-sf",
    label="PPO + SF",
    config_cls=PPOSafetyFilterParams,
    build=build,
    models=models,
    acting=Acting(
        modules=("cost_critic",),
        policy=acting_policy,
        controllers=(UNFILTERED,),
        settings=ActingSettings("safety_filter", resolve_filter),
    ),
)
