"""Resolved RL run configs (the task registry's defaults after overrides) and the skrl agent
factory.

Hyperparameters live with each task (``sonogym.envs.<task>.SPEC.training``): the paper's
appendix tables ``tab:ppo_hype`` and ``tab:a2c_hype``; what the tables leave open comes from
the reference (reference_implementation.md §7.1): KLAdaptiveLR with
kl_threshold 0.008 for both algorithms, values standardised by skrl's RunningStandardScaler,
observations not normalised, entropy scale 0, 128 envs (paper; the reference's default is 64).

Deliberate difference from the reference: ``time_limit_bootstrap=True``. All three tasks end
only by truncation (time limit); skrl 2.x's GAE with bootstrapping off does not cut the
advantage chain at truncations (only at terminations), so the next episode's values would leak
into the last steps of each episode. With it on, skrl adds gamma V(s_T) to the truncated
step's reward and cuts the chain; the trainer feeds it the true final observation s_T
(``SkrlEnvAdapter.final_observations``), not the next episode's first one.

Units: learning rates per optimiser step; ``rollouts`` in env steps per env between updates;
``timesteps`` in env steps per env (skrl's trainer timesteps); ``reward_scale`` and
``obs_scales`` unitless factors (1.0: rewards in the task's own units, observations as the env
emits them: images in [0, 1], path length in m, pose in m and unit quaternion).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from sonogym.envs.registry import check_algo, get_task
from sonogym.envs.spec import A2CParams, PPOParams, SafetyParams

__all__ = ["A2CParams", "PPOParams", "TaskRLConfig", "build_agent", "task_config", "to_jsonable"]


@dataclass(frozen=True)
class TaskRLConfig:
    """Everything a training run of one task needs besides the algorithm's own numbers:
    the task's registry defaults (``sonogym.envs.spec.TrainingDefaults``) after overrides."""

    task: str
    ppo: PPOParams
    a2c: A2CParams
    timesteps: int  # env steps per env (reference trainer timesteps)
    num_envs: int = 128  # paper
    obs_downsample: int = 1  # integer average-pooling factor of image observations
    net: str = "paper"  # conv trunk size: a key of the task's ``trunks`` ("paper", "small")
    obs_scales: dict[str, float] = field(default_factory=dict)  # per entry, unitless
    reward_scale: float = 1.0  # unitless factor on rewards before learning
    init_log_std: float = 0.0  # initial log sigma of the Gaussian policy, action units
    standardize_vectors: bool = False  # running standardisation of vector observations
    env_kwargs: dict[str, Any] = field(default_factory=dict)  # make_vec options
    cost_learning_rate: float = 1e-4  # ppo-sf / ppo-lag: cost network's Adam learning rate
    cost_threshold: float = 0.5  # ppo-sf: filter where Q_c(o, a) > this (cost in [0, 1])
    cost_limit: float = 5.0  # ppo-lag: limit on the mean discounted cost return (cost units)
    pid_gains: tuple[float, float, float] = (0.05, 0.0005, 0.1)  # ppo-lag: Kp, Ki, Kd

    @property
    def env_id(self) -> str:
        return get_task(self.task).env_id

    def params(self, algo: str) -> PPOParams | A2CParams:
        check_algo(self.task, algo)
        return self.a2c if algo == "a2c" else self.ppo


def task_config(task: str, **overrides) -> TaskRLConfig:
    """The task's registry defaults as a ``TaskRLConfig``, with fields replaced
    (``dataclasses.replace`` semantics); an unknown task names the known ones."""
    t = get_task(task).training
    safety = t.safety or SafetyParams()
    base = TaskRLConfig(
        task=task,
        ppo=t.ppo,
        a2c=t.a2c,
        timesteps=t.timesteps,
        num_envs=t.num_envs,
        obs_scales=dict(t.obs_scales),
        reward_scale=t.reward_scale,
        init_log_std=t.init_log_std,
        standardize_vectors=t.standardize_vectors,
        cost_learning_rate=safety.cost_learning_rate,
        cost_threshold=safety.cost_threshold,
        cost_limit=safety.cost_limit,
        pid_gains=safety.pid_gains,
    )
    return dataclasses.replace(base, **overrides)


class RewardScale:
    """skrl ``rewards_shaper``: multiply rewards by a constant (logged returns stay unscaled)."""

    def __init__(self, scale: float) -> None:
        self.scale = float(scale)

    def __call__(self, rewards: torch.Tensor, timestep: int, timesteps: int) -> torch.Tensor:
        return rewards * self.scale


def build_agent(
    cfg: TaskRLConfig,
    algo: str,
    models: dict,
    observation_space,
    action_space,
    num_envs: int,
    out: str | Path,
    device: str | torch.device = "cpu",
    write_interval: int = 0,
    checkpoint_interval: int = 0,
):
    """The skrl agent (PPO or A2C) for ``algo`` on ``cfg.task``, logging into ``out``.

    ``write_interval`` / ``checkpoint_interval`` are in env steps (0 disables). Unsupported
    pairs raise ``ValueError`` naming the supported algorithms. ``ppo-sf`` needs
    ``models["cost_critic"]``, ``ppo-lag`` ``models["cost_value"]``.
    """
    from skrl.agents.torch import ExperimentCfg
    from skrl.agents.torch.a2c import A2C, A2C_CFG
    from skrl.agents.torch.ppo import PPO, PPO_CFG
    from skrl.memories.torch import RandomMemory
    from skrl.resources.preprocessors.torch import RunningStandardScaler
    from skrl.resources.schedulers.torch import KLAdaptiveLR

    p = cfg.params(algo)
    out = Path(out)
    common = dict(
        rollouts=p.rollouts,
        mini_batches=p.mini_batches,
        discount_factor=p.discount_factor,
        gae_lambda=p.gae_lambda,
        learning_rate=p.learning_rate,
        learning_rate_scheduler=KLAdaptiveLR,
        learning_rate_scheduler_kwargs={"kl_threshold": p.kl_threshold},
        value_preprocessor=RunningStandardScaler,
        value_preprocessor_kwargs={"size": 1, "device": device},
        grad_norm_clip=p.grad_norm_clip,
        entropy_loss_scale=p.entropy_loss_scale,
        time_limit_bootstrap=p.time_limit_bootstrap,
        rewards_shaper=RewardScale(cfg.reward_scale) if cfg.reward_scale != 1.0 else None,
        experiment=ExperimentCfg(
            directory=str(out.parent),
            experiment_name=out.name,
            write_interval=write_interval,
            checkpoint_interval=checkpoint_interval,
        ),
    )
    memory = RandomMemory(memory_size=p.rollouts, num_envs=num_envs, device=device)
    if algo == "a2c":
        agent_cfg, cls = A2C_CFG(**common), A2C
    else:
        if algo == "ppo-sf":
            from sonogym.agents.safety_filter import PPO_SF_CFG, PPOSafetyFilter

            cfg_cls, cls = PPO_SF_CFG, PPOSafetyFilter
            common.update(
                cost_learning_rate=cfg.cost_learning_rate, cost_threshold=cfg.cost_threshold
            )
        elif algo == "ppo-lag":
            from sonogym.agents.lagrangian import PPO_LAG_CFG, PPOLagrangian

            cfg_cls, cls = PPO_LAG_CFG, PPOLagrangian
            common.update(
                cost_learning_rate=cfg.cost_learning_rate,
                cost_limit=cfg.cost_limit,
                pid_gains=cfg.pid_gains,
            )
        else:
            cfg_cls, cls = PPO_CFG, PPO
        agent_cfg = cfg_cls(
            **common,
            learning_epochs=p.learning_epochs,
            ratio_clip=p.ratio_clip,
            value_clip=p.value_clip,
            value_loss_scale=p.value_loss_scale,
        )
    return cls(
        models=models,
        memory=memory,
        observation_space=observation_space,
        action_space=action_space,
        device=device,
        cfg=agent_cfg,
    )


def to_jsonable(obj: Any) -> Any:
    """Dataclasses / paths / tuples -> JSON-serialisable values (for the resolved config)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, int | float | str | bool) or obj is None:
        return obj
    return repr(obj)
