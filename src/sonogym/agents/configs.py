"""Resolved RL run configs: the task's defaults (``sonogym.tasks.<task>.agents``) and the
algorithm's config (``sonogym.agents.algorithms``) after the device preset and overrides, as a
run's ``config.json`` stores them; and the agent factory (``build_agent``), which hands the
algorithm's builder what it makes the skrl agent from.

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

from sonogym.agents.algorithms import (
    AgentSetup,
    algo_config,
    algorithm_names,
    check_algo,
    get_algorithm,
)
from sonogym.agents.dagger import DaggerConfig, check_expert
from sonogym.agents.task_defaults import LearningParams, training_defaults
from sonogym.envs.base import check_number_fields
from sonogym.envs.registry import env_config, get_task
from sonogym.runs import lists_to_tuples, to_jsonable

__all__ = [
    "LearningParams",
    "TaskRLConfig",
    "TrainConfig",
    "build_agent",
    "task_config",
    "to_jsonable",
]


@dataclass(frozen=True)
class TaskRLConfig:
    """What a training run of one task needs besides its algorithm's config: the task's
    defaults (``sonogym.agents.task_defaults.TrainingDefaults``) after the preset and
    overrides. ``learning`` is the task's own record, not a copy of its fields."""

    task: str
    timesteps: int  # env steps per env (reference trainer timesteps)
    num_envs: int = 128  # paper
    obs_downsample: int = 1  # integer average-pooling factor of image observations
    net: str = "paper"  # network size: a key of ``networks.NET_SIZES`` (paper, small, lean)
    learning: LearningParams = field(default_factory=LearningParams)  # scales, exploration
    env_kwargs: dict[str, Any] = field(default_factory=dict)  # make_vec options

    @property
    def env_id(self) -> str:
        return get_task(self.task).env_id


def task_config(task: str, preset: str = "paper", **overrides) -> TaskRLConfig:
    """The task's defaults as a ``TaskRLConfig``, with fields replaced
    (``dataclasses.replace`` semantics); an unknown task names the known ones. ``preset``
    "cpu" takes the task's CPU recipe where it has one (``CpuRecipe.env_kwargs``,
    ``timesteps``; its ``net`` is applied by ``resolve_train_config``, its algorithm configs
    by ``algorithms.algo_config``)."""
    t = training_defaults(task)
    cpu = preset == "cpu"
    base = TaskRLConfig(
        task=task,
        timesteps=t.cpu.timesteps if (cpu and t.cpu.timesteps) else t.timesteps,
        num_envs=t.num_envs,
        learning=t.learning,
        env_kwargs=dict(t.cpu.env_kwargs) if cpu else {},
    )
    return dataclasses.replace(base, **overrides)


def upgrade_config(d: dict[str, Any]) -> dict[str, Any]:
    """A run's ``config.json`` in today's layout (a copy; a dict that is not a run's comes
    back as it was):

    * runs written before the learning and safety settings were nested kept them at the top
      level of ``task_config``; they move into their record;
    * runs written before the algorithm registry kept every algorithm's table in
      ``task_config`` ("ppo", "a2c") and the safe-RL settings in ``task_config.safety``; the
      run's own algorithm's become ``algo_params`` (its table and the safety settings its
      config has), and the rest is dropped."""
    tc = d.get("task_config")
    if not isinstance(tc, dict):
        return d
    tc = dict(tc)
    groups = (("learning", {f.name for f in dataclasses.fields(LearningParams)}),
              ("safety", set(_LEGACY_SAFETY) if "ppo" in tc else set()))  # fmt: skip
    for group, names in groups:
        flat = {k: tc.pop(k) for k in list(tc) if k in names}
        nested = tc.get(group)
        if flat or group == "learning":
            tc[group] = {**flat, **nested} if isinstance(nested, dict) else (nested or flat)
    out = {**d, "task_config": tc}
    if "ppo" in tc or "a2c" in tc:  # before the registry
        tables = {k: tc.pop(k) for k in ("ppo", "a2c", "safety") if k in tc}
        algo = d.get("algo")
        table = tables.get(algo if algo in ("ppo", "a2c") else "ppo")
        if isinstance(table, dict):
            cls = _config_cls(algo)
            known = {f.name for f in dataclasses.fields(cls)} if cls else set()
            safety = tables.get("safety") if isinstance(tables.get("safety"), dict) else {}
            out["algo_params"] = {**table, **{k: v for k, v in safety.items() if k in known}}
    return out


#: the safe-RL settings runs kept in ``task_config.safety`` before the algorithm registry
_LEGACY_SAFETY = ("cost_learning_rate", "cost_threshold", "filter_mode", "cost_limit", "pid_gains")


def _config_cls(algo: Any) -> type | None:
    try:
        return get_algorithm(algo).config_cls
    except ValueError:
        return None


#: Options a resumed run may change: how long it runs and where (the rest defines the run).
RESUMABLE_OPTIONS = ("steps", "device", "threads")


@dataclass(frozen=True)
class TrainConfig:
    """The one input of a training run: what ``sonogym train`` resolves and ``config.json``
    stores and loads back (``to_dict`` / ``from_dict``).

    ``rl`` holds the task's resolved settings (envs, network, downsampling, exploration, env
    options, steps as ``rl.timesteps``), ``params`` the algorithm's config (its
    ``AlgorithmSpec.config_cls``); the rest is the run's own."""

    task: str
    algo: str
    rl: TaskRLConfig
    params: Any  # the algorithm's config (``config.json``'s "algo_params")
    seed: int = 0
    preset: str = "paper"  # the device preset the settings resolved from ("cpu", "paper")
    threads: int | None = None  # torch CPU threads (None: torch's default)
    device: str = "cpu"
    checkpoint_interval: int | None = None  # env steps per env; None: ~10 checkpoints
    write_interval: int | None = None  # env steps per env; None: once per update
    #: the checkpoint the weights started from instead of random ones (``warm_start_source``:
    #: checkpoint, run, steps, cpu_s, wall_s of that run by then); None: a fresh start
    init_from: dict[str, Any] | None = None
    #: a DAgger warm start of the policy's mean before RL (``sonogym.agents.dagger``); None:
    #: none
    dagger: DaggerConfig | None = None

    def __post_init__(self) -> None:
        spec = check_algo(self.task, self.algo)
        if self.dagger is not None:
            check_expert(self.task, self.dagger.expert)
        if not isinstance(self.params, spec.config_cls):
            raise TypeError(
                f"{self.algo} trains with a {spec.config_cls.__name__}, got "
                f"{type(self.params).__name__}"
            )
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
            "dagger": None if self.dagger is None else self.dagger.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        """Back from ``to_dict`` (a run's ``config.json``, in any layout ``upgrade_config``
        reads)."""
        d = upgrade_config(d)
        tc = dict(d["task_config"])
        tc["learning"] = LearningParams(**tc["learning"])
        tc["env_kwargs"] = lists_to_tuples(tc.get("env_kwargs", {}))
        names = {f.name for f in dataclasses.fields(TaskRLConfig)}
        rl = TaskRLConfig(**{k: v for k, v in tc.items() if k in names})
        params = get_algorithm(d["algo"]).config_cls(**lists_to_tuples(d["algo_params"]))
        return cls(
            task=d["task"],
            algo=d["algo"],
            rl=rl,
            params=params,
            seed=d.get("seed", 0),
            preset=d.get("preset", "paper"),
            threads=d.get("threads"),
            device=d.get("device", "cpu"),
            checkpoint_interval=d.get("checkpoint_interval"),
            write_interval=d.get("write_interval"),
            init_from=d.get("init_from"),
            dagger=DaggerConfig(**d["dagger"]) if d.get("dagger") else None,
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
    """A run's settings in one order: the task's defaults and the algorithm's config for it,
    then the device preset (``sonogym.agents.presets``: envs, network size, image downsampling,
    threads; the task's ``cpu`` recipe), then the explicit options (None: not given)."""
    from sonogym.agents.presets import resolve_preset

    check_algo(task, algo)
    p = resolve_preset(preset, device)
    defaults = training_defaults(task)
    rl = task_config(
        task,
        p.name,
        num_envs=p.num_envs,
        net=defaults.cpu.net if (p.name == "cpu" and defaults.cpu.net) else p.net,
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
        params=algo_config(task, algo, p.name),
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
#: Task-config settings ``apply_settings`` takes by name; besides them ``<algorithm>.<field>``
#: (a field of the run's algorithm config, e.g. ``ppo.learning_rate``) and ``env.<option>``
#: (an env option).
TASK_KEYS = ("num_envs", "net", "obs_downsample", *LEARNING_KEYS)


def check_setting_key(key: str, what: str = "setting") -> None:
    """Refuse a key ``apply_settings`` does not know, listing the ones it does."""
    head, _, field = key.partition(".")
    known = head in algorithm_names() or head == "env"
    if not (key in TASK_KEYS or (known and field)):
        raise ValueError(
            f"unknown {what} {key!r}: use one of {list(TASK_KEYS)} or <algorithm>.<field> "
            f"(algorithms: {', '.join(algorithm_names())}; in a sweep grid also env.<option>; "
            "seeds: --seed / --seeds)"
        )


def apply_settings(base: TrainConfig, params: dict[str, Any], what: str = "setting") -> TrainConfig:
    """``base`` with the given settings (keys as ``check_setting_key`` lists them; ``seed``
    sets the seed), checked as a run's config is (an unknown setting, a value the algorithm's
    config, the task config or the env config refuses: ``ValueError`` naming it), without
    building anything. The training sweeps' grid points and ``sonogym train --set``.

    ``<algorithm>.<field>`` sets a field of the run's algorithm config; ``<algorithm>`` is the
    run's algorithm or one whose config the run's extends (``ppo.learning_rate`` on a
    ``ppo-sf`` run)."""
    rl, algo_params = base.rl, base.params
    for key, v in params.items():
        if key == "seed":
            continue
        check_setting_key(key, what)
        head, _, field = key.partition(".")
        if head in algorithm_names():
            algo_params = _set_algo_field(algo_params, base.algo, head, field, v, key, what)
        elif head == "env":
            rl = dataclasses.replace(rl, env_kwargs={**rl.env_kwargs, field: v})
        elif key in LEARNING_KEYS:
            rl = dataclasses.replace(rl, learning=dataclasses.replace(rl.learning, **{key: v}))
        else:
            rl = dataclasses.replace(rl, **{key: v})
    seed = int(params.get("seed", base.seed))
    return dataclasses.replace(base, rl=rl, params=algo_params, seed=seed)


def _set_algo_field(config: Any, algo: str, head: str, field: str, v: Any, key: str, what: str):
    """``config`` (the run's ``algo`` config) with ``field`` set to ``v`` (setting ``key``,
    ``head`` the algorithm it names)."""
    cls = get_algorithm(head).config_cls
    if not isinstance(config, cls):
        raise ValueError(
            f"{what} {key!r}: a {head} setting, but this run trains {algo}; use {algo}.<field>"
        )
    names = [f.name for f in dataclasses.fields(cls)]
    if field not in names:
        raise ValueError(
            f"{what} {key!r}: {head} has no setting {field!r}; its settings are {names}"
        )
    return dataclasses.replace(config, **{field: v})


def _env_default(task: str, key: str) -> Any:
    """The env config's default for option ``key`` (what a run that did not set it used)."""
    cls = get_task(task).config_cls
    for f in dataclasses.fields(cls):
        if f.name == key:
            return lists_to_tuples(f.default) if f.default is not dataclasses.MISSING else None
    raise ValueError(f"unknown {task} env option {key!r}")


def build_agent(
    cfg: TrainConfig,
    models: dict,
    observation_space,
    action_space,
    out: str | Path,
    write_interval: int = 0,
    state_space=None,
):
    """The skrl agent of the run ``cfg`` describes (its algorithm's ``build``), logging into
    ``out`` every ``write_interval`` env steps (0: never). ``models`` holds "policy" and
    "value" and the algorithm's own (its ``models`` hook); ``state_space`` (a privileged
    critic's state, ``SkrlEnvAdapter.state_space``) adds skrl's states, which a running
    standardiser scales before the critic reads them."""
    setup = AgentSetup(
        task=cfg.task, config=cfg.params, learning=cfg.rl.learning, models=models,
        observation_space=observation_space, action_space=action_space,
        state_space=state_space, num_envs=cfg.rl.num_envs, out=Path(out),
        device=str(cfg.device), write_interval=write_interval,
    )  # fmt: skip
    return get_algorithm(cfg.algo).build(setup)
