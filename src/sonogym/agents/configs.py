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

from sonogym.envs.base import check_number_fields
from sonogym.envs.registry import check_algo, env_config, get_task
from sonogym.envs.spec import A2CParams, LearningParams, PPOParams, SafetyParams
from sonogym.runs import lists_to_tuples, to_jsonable

__all__ = [
    "A2CParams",
    "LearningParams",
    "PPOParams",
    "SafetyParams",
    "TaskRLConfig",
    "build_agent",
    "task_config",
    "to_jsonable",
]


@dataclass(frozen=True)
class TaskRLConfig:
    """Everything a training run of one task needs besides the algorithm's own numbers:
    the task's registry defaults (``sonogym.envs.spec.TrainingDefaults``) after overrides.
    ``learning`` and ``safety`` are the registry's own records, not copies of their fields."""

    task: str
    ppo: PPOParams
    a2c: A2CParams
    timesteps: int  # env steps per env (reference trainer timesteps)
    num_envs: int = 128  # paper
    obs_downsample: int = 1  # integer average-pooling factor of image observations
    net: str = "paper"  # network size: a key of ``networks.NET_SIZES`` (paper, small, lean)
    learning: LearningParams = field(default_factory=LearningParams)  # scales, exploration
    env_kwargs: dict[str, Any] = field(default_factory=dict)  # make_vec options
    safety: SafetyParams = field(default_factory=SafetyParams)  # ppo-sf / ppo-lag settings

    @property
    def env_id(self) -> str:
        return get_task(self.task).env_id

    def params(self, algo: str) -> PPOParams | A2CParams:
        check_algo(self.task, algo)
        return self.a2c if algo == "a2c" else self.ppo


def task_config(task: str, preset: str = "paper", **overrides) -> TaskRLConfig:
    """The task's registry defaults as a ``TaskRLConfig``, with fields replaced
    (``dataclasses.replace`` semantics); an unknown task names the known ones. ``preset``
    "cpu" takes the task's CPU recipe where it has one (``TrainingDefaults.ppo_cpu``,
    ``env_kwargs_cpu``, ``timesteps_cpu``; ``net_cpu`` is applied by ``resolve_train_config``)."""
    t = get_task(task).training
    base = TaskRLConfig(
        task=task,
        ppo=t.ppo_cpu if (preset == "cpu" and t.ppo_cpu is not None) else t.ppo,
        a2c=t.a2c,
        timesteps=t.timesteps_cpu if (preset == "cpu" and t.timesteps_cpu) else t.timesteps,
        num_envs=t.num_envs,
        learning=t.learning,
        safety=t.safety or SafetyParams(),
        env_kwargs=dict(t.env_kwargs_cpu) if preset == "cpu" else {},
    )
    return dataclasses.replace(base, **overrides)


def nested_task_config(tc: dict[str, Any]) -> dict[str, Any]:
    """A ``config.json`` ``task_config`` in today's layout: runs written before the learning
    and safety settings were nested (``learning``, ``safety``) kept their fields at the top
    level; they move into their record (a field the run never wrote stays absent)."""
    out = dict(tc)
    for group, cls in (("learning", LearningParams), ("safety", SafetyParams)):
        names = {f.name for f in dataclasses.fields(cls)}
        flat = {k: out.pop(k) for k in list(out) if k in names}
        nested = out.get(group)
        out[group] = {**flat, **nested} if isinstance(nested, dict) else (nested or flat)
    return out


#: Options a resumed run may change: how long it runs and where (the rest defines the run).
RESUMABLE_OPTIONS = ("steps", "device", "threads")


@dataclass(frozen=True)
class TrainConfig:
    """The one input of a training run: what ``sonogym train`` resolves and ``config.json``
    stores and loads back (``to_dict`` / ``from_dict``).

    ``rl`` holds the task's resolved settings (hyperparameters, envs, network, downsampling,
    env options, steps as ``rl.timesteps``); the rest is the run's own."""

    task: str
    algo: str
    rl: TaskRLConfig
    seed: int = 0
    preset: str = "paper"  # the device preset the settings resolved from ("cpu", "paper")
    threads: int | None = None  # torch CPU threads (None: torch's default)
    device: str = "cpu"
    checkpoint_interval: int | None = None  # env steps per env; None: ~10 checkpoints
    write_interval: int | None = None  # env steps per env; None: once per update
    #: the checkpoint the weights started from instead of random ones (``warm_start_source``:
    #: checkpoint, run, steps, cpu_s, wall_s of that run by then); None: a fresh start
    init_from: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        check_algo(self.task, self.algo)
        check_number_fields(self.rl)  # NaN, inf, 2.5 envs; 2.0 envs becomes 2
        for name in ("num_envs", "timesteps", "obs_downsample"):
            v = getattr(self.rl, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                flag = {"num_envs": "envs", "timesteps": "steps"}.get(name, name)
                raise ValueError(f"{flag} must be a positive integer, got {v!r}")
        learning = self.rl.learning
        final, anneal = learning.final_log_std, learning.anneal_steps
        if isinstance(anneal, bool) or not isinstance(anneal, int) or anneal < 0:
            raise ValueError(f"anneal_steps must be an integer >= 0, got {anneal!r}")
        frozen = learning.standardize_steps
        if isinstance(frozen, bool) or not isinstance(frozen, int) or frozen < 0:
            raise ValueError(f"standardize_steps must be an integer >= 0, got {frozen!r}")
        if final is not None and final > learning.init_log_std:
            raise ValueError(
                f"final_log_std {final} is above init_log_std {learning.init_log_std}: the "
                "ceiling only lowers sigma; pass final_log_std <= init_log_std, or None for none"
            )
        p = self.params
        if learning.privileged_critic and p.rollouts * self.rl.num_envs < 2 * p.mini_batches:
            raise ValueError(  # skrl's running scaler takes each mini-batch's (unbiased) variance
                f"privileged_critic needs >= 2 samples per mini-batch: {p.rollouts} rollouts x "
                f"{self.rl.num_envs} envs / {p.mini_batches} mini-batches; use more envs or "
                "fewer mini-batches"
            )
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")
        for name in ("checkpoint_interval", "write_interval"):
            v = getattr(self, name)
            if v is not None and v < 1:
                raise ValueError(f"{name} must be >= 1 env step, got {v}")
        from sonogym.agents.networks import net_size

        net_size(self.rl.net)
        env_config(self.task, self.rl.env_kwargs)  # every env option, as the env will read it

    @property
    def steps(self) -> int:
        """Env steps per env in total (resumed ones included)."""
        return self.rl.timesteps

    @property
    def params(self) -> PPOParams | A2CParams:
        return self.rl.params(self.algo)

    def intervals(self) -> tuple[int, int]:
        """(checkpoint, TensorBoard write) intervals in env steps: the given ones, else about
        ten checkpoints at update boundaries and one write per update."""
        r = self.params.rollouts
        ckpt = self.checkpoint_interval or r * max(1, round(self.steps / 10 / r))
        return ckpt, self.write_interval or r

    def to_dict(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "algo": self.algo,
            "seed": self.seed,
            "preset": self.preset,
            "threads": self.threads,
            "device": self.device,
            "num_envs": self.rl.num_envs,
            "steps": self.steps,
            "env_id": self.rl.env_id,
            "checkpoint_interval": self.checkpoint_interval,
            "write_interval": self.write_interval,
            "task_config": to_jsonable(self.rl),
            "algo_params": to_jsonable(self.params),
            "init_from": self.init_from,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """Back from ``to_dict`` (a run's ``config.json``)."""
        tc = nested_task_config(d["task_config"])
        tc["ppo"] = PPOParams(**tc["ppo"])
        tc["a2c"] = A2CParams(**tc["a2c"])
        tc["learning"] = LearningParams(**tc["learning"])
        tc["safety"] = SafetyParams(**lists_to_tuples(tc["safety"]))
        tc["env_kwargs"] = lists_to_tuples(tc.get("env_kwargs", {}))
        names = {f.name for f in dataclasses.fields(TaskRLConfig)}
        rl = TaskRLConfig(**{k: v for k, v in tc.items() if k in names})
        return cls(
            task=d["task"],
            algo=d["algo"],
            rl=rl,
            seed=d.get("seed", 0),
            preset=d.get("preset", "paper"),
            threads=d.get("threads"),
            device=d.get("device", "cpu"),
            checkpoint_interval=d.get("checkpoint_interval"),
            write_interval=d.get("write_interval"),
            init_from=d.get("init_from"),
        )


def resolve_train_config(
    task: str,
    algo: str,
    *,
    preset: str = "auto",
    device: str = "cpu",
    seed: int | None = None,
    envs: int | None = None,
    steps: int | None = None,
    net: str | None = None,
    obs_downsample: int | None = None,
    threads: int | None = None,
    env_kwargs: dict[str, Any] | None = None,
    checkpoint_interval: int | None = None,
    write_interval: int | None = None,
) -> TrainConfig:
    """A run's settings in one order: the task's registry defaults, then the device preset
    (``sonogym.agents.presets``: envs, network size, image downsampling, threads), then the
    explicit options (None: not given)."""
    from sonogym.agents.presets import resolve_preset

    check_algo(task, algo)
    p = resolve_preset(preset, device)
    defaults = get_task(task).training
    rl = task_config(
        task,
        p.name,
        num_envs=p.num_envs,
        net=defaults.net_cpu if (p.name == "cpu" and defaults.net_cpu) else p.net,
        obs_downsample=p.obs_downsample(defaults.image_height),
    )
    given = {"num_envs": envs, "timesteps": steps, "net": net, "obs_downsample": obs_downsample}
    rl = dataclasses.replace(rl, **{k: v for k, v in given.items() if v is not None})
    rl = dataclasses.replace(rl, env_kwargs={**rl.env_kwargs, **lists_to_tuples(env_kwargs or {})})
    mode = rl.env_kwargs.get("obs_mode", get_task(task).default_obs_mode)
    if mode_scales := defaults.obs_scales_by_mode.get(mode):
        scales = {**rl.learning.obs_scales, **mode_scales}
        rl = dataclasses.replace(rl, learning=dataclasses.replace(rl.learning, obs_scales=scales))
    return TrainConfig(
        task=task,
        algo=algo,
        rl=rl,
        seed=0 if seed is None else seed,
        preset=p.name,
        threads=p.threads if threads is None else threads,
        device=str(device),
        checkpoint_interval=checkpoint_interval,
        write_interval=write_interval,
    )


def resume_config(saved: TrainConfig, **explicit: Any) -> TrainConfig:
    """The saved config of a run being resumed, with the explicit options (None: not given)
    of ``resolve_train_config`` applied: ``steps``, ``device`` and ``threads`` may change;
    any other option that differs from the saved run is refused, naming it."""
    given = {k: v for k, v in explicit.items() if v is not None}
    current = {
        "task": saved.task,
        "algo": saved.algo,
        "seed": saved.seed,
        "envs": saved.rl.num_envs,
        "net": saved.rl.net,
        "obs_downsample": saved.rl.obs_downsample,
        "preset": saved.preset,
        "checkpoint_interval": saved.checkpoint_interval,
        "write_interval": saved.write_interval,
    }
    conflicts = []
    for k, v in given.items():
        if k in RESUMABLE_OPTIONS:
            continue
        if k == "env_kwargs":
            for ek, ev in lists_to_tuples(v).items():
                old = saved.rl.env_kwargs.get(ek, _env_default(saved.task, ek))
                if lists_to_tuples(ev) != old:
                    conflicts.append(f"{ek} {ev!r} (run: {old!r})")
        elif k == "preset":
            if v not in ("auto", saved.preset):
                conflicts.append(f"preset {v!r} (run: {saved.preset!r})")
        elif k in current and v != current[k]:
            conflicts.append(f"{k} {v!r} (run: {current[k]!r})")
        elif k not in current:
            raise TypeError(f"unknown training option {k!r}")
    if conflicts:
        raise ValueError(
            "cannot resume with options that differ from the run's config.json: "
            + "; ".join(conflicts)
            + ". Drop them to continue the run as it was, or start a new run (another --out)"
        )
    rl = saved.rl
    if "steps" in given:
        rl = dataclasses.replace(rl, timesteps=given["steps"])
    return dataclasses.replace(
        saved,
        rl=rl,
        device=str(given.get("device", saved.device)),
        threads=given.get("threads", saved.threads),
    )


#: Settings of the learning (``TaskRLConfig.learning``, a ``LearningParams``), named flat.
LEARNING_KEYS = (
    "reward_scale", "init_log_std", "final_log_std", "anneal_steps", "mean_bound_penalty",
    "standardize_steps", "kl_follows_sigma", "privileged_critic",
)  # fmt: skip
#: Task-config settings ``apply_settings`` takes by name; besides them ``ppo.<field>``,
#: ``a2c.<field>`` (the algorithm's table) and ``env.<option>`` (an env option).
TASK_KEYS = ("num_envs", "net", "obs_downsample", *LEARNING_KEYS)


def check_setting_key(key: str, what: str = "setting") -> None:
    """Refuse a key ``apply_settings`` does not know, listing the ones it does."""
    head, _, field = key.partition(".")
    ok = key in TASK_KEYS or (head in ("ppo", "a2c") and field) or (head == "env" and field)
    if not ok:
        raise ValueError(
            f"unknown {what} {key!r}: use one of {list(TASK_KEYS)}, ppo.<field> or "
            "a2c.<field> (in a sweep grid also env.<option>; seeds: --seed / --seeds)"
        )


def apply_settings(base: TrainConfig, params: dict[str, Any], what: str = "setting") -> TrainConfig:
    """``base`` with the given settings (keys as ``check_setting_key`` lists them; ``seed``
    sets the seed), checked as a run's config is (an unknown setting, a value the algorithm's
    table, the task config or the env config refuses: ``ValueError`` naming it), without
    building anything. The training sweeps' grid points and ``sonogym train --set``."""
    rl = base.rl
    for key, v in params.items():
        if key == "seed":
            continue
        check_setting_key(key, what)
        head, _, field = key.partition(".")
        if head in ("ppo", "a2c"):
            names = [f.name for f in dataclasses.fields(getattr(rl, head))]
            if field not in names:
                raise ValueError(
                    f"{what} {key!r}: {head} has no setting {field!r}; its settings are {names}"
                )
            table = dataclasses.replace(getattr(rl, head), **{field: v})
            rl = dataclasses.replace(rl, **{head: table})
        elif head == "env":
            rl = dataclasses.replace(rl, env_kwargs={**rl.env_kwargs, field: v})
        elif key in LEARNING_KEYS:
            rl = dataclasses.replace(rl, learning=dataclasses.replace(rl.learning, **{key: v}))
        else:
            rl = dataclasses.replace(rl, **{key: v})
    return dataclasses.replace(base, rl=rl, seed=int(params.get("seed", base.seed)))


def _env_default(task: str, key: str) -> Any:
    """The env config's default for option ``key`` (what a run that did not set it used)."""
    cls = get_task(task).config_cls
    for f in dataclasses.fields(cls):
        if f.name == key:
            return lists_to_tuples(f.default) if f.default is not dataclasses.MISSING else None
    raise ValueError(f"unknown {task} env option {key!r}")


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
    state_space=None,
):
    """The skrl agent for ``algo`` (PPO, A2C, or PPO with a safety filter's cost critic or a
    Lagrangian cost value) on ``cfg.task``, logging into ``out``.

    ``write_interval`` / ``checkpoint_interval`` are in env steps (0 disables). ``state_space``
    (a privileged critic's state, ``SkrlEnvAdapter.state_space``) adds skrl's states, which a
    running standardiser scales before the critic reads them. Unsupported
    pairs raise ``ValueError`` naming the supported algorithms. ``ppo-sf`` needs
    ``models["cost_critic"]``, ``ppo-lag`` ``models["cost_value"]``.
    """
    from skrl.agents.torch import ExperimentCfg
    from skrl.agents.torch.a2c import A2C, A2C_CFG
    from skrl.agents.torch.ppo import PPO, PPO_CFG
    from skrl.memories.torch import RandomMemory
    from skrl.resources.preprocessors.torch import RunningStandardScaler
    from skrl.resources.schedulers.torch import KLAdaptiveLR

    p, reward_scale = cfg.params(algo), cfg.learning.reward_scale
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
        rewards_shaper=RewardScale(reward_scale) if reward_scale != 1.0 else None,
        state_preprocessor=RunningStandardScaler if state_space is not None else None,
        state_preprocessor_kwargs=(
            {"size": state_space, "device": device} if state_space is not None else {}
        ),
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
                cost_learning_rate=cfg.safety.cost_learning_rate,
                cost_threshold=cfg.safety.cost_threshold,
            )
        elif algo == "ppo-lag":
            from sonogym.agents.lagrangian import PPO_LAG_CFG, PPOLagrangian

            cfg_cls, cls = PPO_LAG_CFG, PPOLagrangian
            common.update(
                cost_learning_rate=cfg.safety.cost_learning_rate,
                cost_limit=cfg.safety.cost_limit,
                pid_gains=cfg.safety.pid_gains,
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
    agent = cls(
        models=models,
        memory=memory,
        observation_space=observation_space,
        state_space=state_space,
        action_space=action_space,
        device=device,
        cfg=agent_cfg,
    )
    use_multi_tensor_optimizers(agent)
    return agent


def use_multi_tensor_optimizers(agent) -> None:
    """Switch every optimiser of ``agent`` to torch's multi-tensor (``foreach``) update.

    Why: on CPU torch defaults to one small kernel per parameter tensor; the surgery state
    network's Adam step took 3.2 ms that way and 1.6 ms with ``foreach``, with bit-identical
    weights (CUDA already defaults to it). Call again after loading an optimiser's state:
    ``load_state_dict`` restores the saved flag."""
    for module in agent.checkpoint_modules.values():
        if isinstance(module, torch.optim.Optimizer):
            module.defaults["foreach"] = True
            for group in module.param_groups:
                group["foreach"] = True
