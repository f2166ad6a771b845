"""Train a skrl agent on a SonoGym task with any registered algorithm
(``sonogym.agents.algorithms``: ``ppo``, ``a2c``, ``ppo-sf``, ``ppo-lag``, or one of your own;
the task's agents module lists the ones it has a config for).

``train(task, algo, ...)`` resolves a ``TrainConfig`` (task defaults, device preset, explicit
options) or, with ``resume=True``, loads the run's own; ``run_training(cfg, out)`` runs it.
Writes into ``out/``:

* ``config.json``: the resolved run config (``TrainConfig.to_dict`` plus the observation
  layout, action box, versions and the step a resumed run started from), written atomically;
* TensorBoard event files (skrl's writer: losses, rewards, learning rate; plus the tasks'
  episode metrics under ``Episode / <metric>``);
* ``checkpoints/agent_<t>.pt``: agent checkpoints (policy = value module, optimiser, value
  standardiser, observation standardiser) after t env steps per env, written atomically
  (temporary file + rename); ``agent_0.pt`` holds the initial weights (after the DAgger warm
  start where the run has one: ``sonogym.agents.dagger``), the newest one the final policy.
  They load with ``weights_only=True`` (``checkpoint.read_checkpoint``).

The loop is skrl's sequential trainer loop written out, for one reason: with SAME_STEP
autoreset the observation after a truncation is the next episode's first one, so the loop hands
skrl the true final observation (``info["final_obs"]``) as ``next_observations`` for
time-limit bootstrapping, and the reset one as the next step's input.

Output folders follow ``sonogym.runs.prepare_output``: an existing run is continued only with
``resume`` and replaced only with ``force`` (only a folder marked as a training run, holding
only what training and evaluation write; what it deletes is logged), and the folder is locked
while a run writes it (a second run into it is refused, naming the first one's pid).
``resume`` reloads ``config.json`` before touching anything (an explicit option that differs
is refused, naming it; ``steps``, ``device`` and ``threads`` may change) and continues from the
newest readable checkpoint (weights, optimiser, standardisers; the envs restart from a fresh
reset and the rollout memory is empty). Ctrl-C saves a checkpoint at the last completed step
and says how to resume.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sonogym.agents.adapter import SkrlEnvAdapter
from sonogym.agents.algorithms import ModelSetup, get_algorithm
from sonogym.agents.algorithms.common import use_multi_tensor_optimizers
from sonogym.agents.checkpoint import (
    RL_RUN,
    check_obs_version,
    read_checkpoint,
    set_log_std_ceiling,
)
from sonogym.agents.configs import (
    TaskRLConfig,
    TrainConfig,
    apply_settings,
    build_agent,
    resolve_train_config,
    resume_config,
    to_jsonable,
)
from sonogym.agents.dagger import DaggerConfig, run_dagger
from sonogym.agents.networks import log_std_ceiling, make_models
from sonogym.agents.task_defaults import LearningParams
from sonogym.envs.identity import identity, stamp
from sonogym.envs.registry import check_task_name, get_task, make_vec
from sonogym.progress import progress_bar
from sonogym.runs import (
    SHIPPED_WEIGHTS,
    RunFolder,
    TrainingInterrupted,
    atomic_torch_save,
    atomic_write_json,
    deleted_message,
    prepare_output,
    read_json,
)


@dataclass(frozen=True)
class TrainResult:
    out: Path  # run directory
    checkpoint: Path  # the final checkpoint
    steps: int  # env steps per env done in total (including resumed ones)
    speed: dict[str, float] | None = None  # ``TrainingSpeed.figures()`` since start or resume


def make_env(cfg: TaskRLConfig, num_envs: int, device: str | torch.device):
    """The task's batched env (``gymnasium.make_vec``) with ``cfg.env_kwargs`` (device set
    here)."""
    return make_vec(cfg.task, num_envs, **{**cfg.env_kwargs, "device": str(device)})


def train(
    task: str,
    algo: str,
    envs: int | None = None,
    steps: int | None = None,
    seed: int | None = None,
    out: str | Path | None = None,
    *,
    patients: tuple | None = None,
    simulator: str | None = None,
    obs_downsample: int | None = None,
    net: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    preset: str | None = None,
    threads: int | None = None,
    device: str | None = None,
    resume: bool = False,
    force: bool = False,
    checkpoint_interval: int | None = None,
    write_interval: int | None = None,
    settings: dict[str, Any] | None = None,
    init_from: str | Path | None = None,
    dagger: DaggerConfig | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> TrainResult:
    """Train ``algo`` on ``task`` (options None: from the task's defaults and the preset).

    Args:
        envs: parallel envs; steps: env steps per env in total, resumed ones included.
        seed: seeds torch and the envs' first reset (default 0).
        out: run directory (default ``runs/<task>-<algo>-s<seed>``).
        patients, simulator, env_kwargs: env options (``make_vec`` keywords).
        obs_downsample, net, threads: override the preset's.
        preset: "auto" (default), "cpu" or "paper" (``sonogym.agents.presets``).
        resume: continue the run in ``out`` (its ``config.json``); force: replace it.
        checkpoint_interval, write_interval: in env steps (default: about 10 checkpoints at
            update boundaries; TensorBoard once per update).
        settings: training settings by name (``configs.apply_settings``: ``final_log_std``,
            ``ppo.learning_rate``, ``env.<option>``, ...), applied last.
        init_from: an RL checkpoint (``RUN/checkpoints/agent_<t>.pt``) or a shipped policy's
            folder whose weights the run starts from instead of random ones
            (``warm_start_source``); fine-tuning.
        dagger: warm-start the policy's mean by DAgger from a privileged expert before the
            algorithm's first step (``sonogym.agents.dagger``; after ``init_from``'s weights
            are loaded, where both are given).
        progress: show the progress with the ETA (``sonogym.progress``: a bar on a terminal,
            a line every few percent in a log); log: where the start summary goes (default:
            printed when ``progress``).
    """
    kw = dict(env_kwargs or {})
    if patients is not None:
        kw["patients"] = tuple(patients)
    if simulator is not None:
        kw["simulator"] = simulator
    explicit = dict(
        seed=seed, envs=envs, steps=steps, net=net, obs_downsample=obs_downsample,
        threads=threads, env_kwargs=kw or None, checkpoint_interval=checkpoint_interval,
        write_interval=write_interval, device=device,
    )  # fmt: skip
    out = Path(out or f"runs/{task}-{algo}-s{seed or 0}")
    if resume:
        if settings or init_from is not None or dagger is not None:
            raise ValueError(
                "settings, init_from and dagger define a new run; a resumed run keeps its own. "
                "Drop them to continue the run, or start a new one in another out folder"
            )
        if not (out / "config.json").is_file():
            raise FileNotFoundError(f"nothing to resume: {out} holds no training run")
        saved = load_train_config(out)
        if (saved.task, saved.algo) != (task, algo):
            raise ValueError(
                f"{out} is a {saved.task}/{saved.algo} run; cannot resume it as {task}/{algo}"
            )
        cfg = resume_config(saved, preset=preset, **explicit)
    else:
        cfg = resolve_train_config(
            task, algo, preset=preset or "auto", **{**explicit, "device": device or "cpu"}
        )
        if settings:
            cfg = apply_settings(cfg, settings)
        if init_from is not None:
            cfg = dataclasses.replace(cfg, init_from=warm_start_source(init_from, cfg))
        if dagger is not None:
            cfg = dataclasses.replace(cfg, dagger=dagger)
    if log is None:
        log = print if progress else _quiet
    return run_training(cfg, out, resume=resume, force=force, progress=progress, log=log)


#: RSS growth of training per env and per byte of its rollout observations (rollouts x obs
#: floats x 4), beyond the env's own: 64-step cpu-preset runs at 1 mm measured 1.9 (navigation,
#: 4 -> 128 envs), 2.6 (reconstruction, 4 -> 32 envs, at the update's peak) and 3.7 (surgery,
#: likewise): skrl's memory, the minibatches sampled from it and the update's activations.
TRAINING_MEMORY_FACTOR = 4.0


def check_training_memory(cfg: TrainConfig, obs_floats: int) -> None:
    """Refuse a run whose rollout memory and update would not fit the device's free memory
    (the env is built by now: what it holds is no longer free)."""
    from sonogym.memory import check_fits, free_memory

    r, n = cfg.params.rollouts, cfg.rl.num_envs
    check_fits(
        TRAINING_MEMORY_FACTOR * r * n * obs_floats * 4, free_memory(cfg.device),
        f"{cfg.algo} training of {n} envs ({r} rollout steps of {obs_floats} observation "
        "floats each)", "memory",
        "use fewer envs (--envs), a larger --obs-downsample, or fewer rollouts",
    )  # fmt: skip


def load_train_config(out: str | Path) -> TrainConfig:
    """The ``TrainConfig`` a run folder was trained with (its ``config.json``)."""
    d = read_json(Path(out) / "config.json", "`sonogym train` run folder", ("task", "algo"))
    check_task_name(d["task"], Path(out) / "config.json")
    if "task_config" in d:
        check_obs_version(d, Path(out) / "config.json")
    try:
        return TrainConfig.from_dict(d)
    except (KeyError, TypeError) as e:
        raise ValueError(
            f"{Path(out) / 'config.json'} does not describe a training run ({e!r}); restore it "
            "or start a new run"
        ) from None


#: ``on_checkpoint(steps, checkpoint, metrics)``: called after each checkpoint is written
#: (and the final one) with the mean episode metrics of the episodes that ended since the last
#: call (empty if none did)
CheckpointCallback = Callable[[int, Path, dict[str, float]], None]


def run_training(
    cfg: TrainConfig,
    out: str | Path,
    resume: bool = False,
    force: bool = False,
    progress: bool = True,
    log: Callable[[str], None] = print,
    on_checkpoint: CheckpointCallback | None = None,
) -> TrainResult:
    """Run the training ``cfg`` describes into ``out`` (see the module docstring); the run
    folder is locked while it runs."""
    out = Path(out)
    with prepare_output(out, resume=resume, force=force, kind="rl-run") as folder:
        if folder.deleted:
            log(deleted_message(out, folder.deleted))
        return _run_training(cfg, out, resume, progress, log, on_checkpoint)


def _run_training(
    cfg: TrainConfig,
    out: Path,
    resume: bool,
    progress: bool,
    log: Callable[[str], None],
    on_checkpoint: CheckpointCallback | None,
) -> TrainResult:
    start_ckpt = _resume_point(cfg, out, log) if resume else None
    start = start_ckpt.step if start_ckpt else 0
    threads_before = torch.get_num_threads()
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    env = make_env(cfg.rl, cfg.rl.num_envs, cfg.device)
    try:
        run = _set_up(cfg, out, env, start)
        if start_ckpt is not None:
            load_agent(run.agent, start_ckpt.path)
        elif cfg.init_from is not None:
            warm_start(run.agent, cfg.init_from, run.adapter)
        if start_ckpt is None and cfg.dagger is not None:
            run.dagger = run_dagger(
                cfg.dagger, cfg.task, run.adapter, run.models["policy"], cfg.seed, log
            )
        _write_run_config(cfg, out, run, start, resume)
        if start_ckpt is None:
            run.ckpt_dir.mkdir(parents=True, exist_ok=True)
            save_agent(run.agent, run.ckpt_dir / "agent_0.pt")  # the initial weights
        return _train_loop(cfg, out, run, start, progress, log, on_checkpoint)
    finally:
        env.close()
        torch.set_num_threads(threads_before)


@dataclass
class _Run:
    """What a training run steps: the env's skrl view, the networks, the agent, and where and
    how often checkpoints and TensorBoard go (env steps per env)."""

    adapter: SkrlEnvAdapter
    models: dict
    agent: Any
    ckpt_dir: Path
    ckpt_interval: int
    write_interval: int
    dagger: dict[str, Any] | None = None  # what the DAgger warm start gave (``run_dagger``)


def _resume_point(cfg: TrainConfig, out: Path, log: Callable[[str], None]):
    """The checkpoint a resumed run continues from (its newest readable one), refused if there
    is none or it has the requested steps already."""
    start_ckpt = RunFolder(out, RL_RUN).newest_readable_checkpoint(warn=log)
    if start_ckpt is None:
        raise FileNotFoundError(f"nothing to resume: no readable checkpoint in {out}")
    if start_ckpt.step >= cfg.steps:
        raise ValueError(
            f"{out} already has {start_ckpt.step} steps >= the requested {cfg.steps}; "
            "pass a larger --steps to train further"
        )
    return dataclasses.replace(start_ckpt, state=None)  # the agent reads it


def _set_up(cfg: TrainConfig, out: Path, env, start: int) -> _Run:
    """The adapter, networks and agent of run ``cfg`` on ``env`` from env step ``start``; the
    training memory is checked before skrl allocates it."""
    from skrl.trainers.torch import SequentialTrainerCfg

    learning = cfg.rl.learning
    adapter = SkrlEnvAdapter(
        env, cfg.rl.obs_downsample, learning.obs_scales, seed=cfg.seed + start,
        standardize_vectors=learning.standardize_vectors,
        stagger_episodes=learning.stagger_episodes, privileged_state=learning.privileged_critic,
    )  # fmt: skip
    adapter.update_stats = statistics_update(cfg.rl, start)
    check_training_memory(cfg, adapter.observation_space.shape[0])
    models = _models(cfg, adapter)
    ckpt_interval, write_interval = cfg.intervals()
    agent = build_agent(
        cfg, models, adapter.observation_space, adapter.action_space, out,
        write_interval=write_interval, state_space=adapter.state_space,
    )  # fmt: skip
    if adapter.standardizer is not None:  # saved and restored with the agent
        agent.checkpoint_modules["obs_standardizer"] = adapter.standardizer
    agent.init(trainer_cfg=SequentialTrainerCfg(timesteps=cfg.steps))
    return _Run(adapter, models, agent, out / "checkpoints", ckpt_interval, write_interval)


def _write_run_config(cfg: TrainConfig, out: Path, run: _Run, start: int, resume: bool) -> None:
    """``config.json``: the resolved config, the interface, versions and benchmark identity;
    a resumed run made under another identity is refused."""
    made_with = identity(cfg.task, cfg.rl.env_kwargs)
    if resume:
        saved = read_json(out / "config.json", "`sonogym train` run folder")
        before = saved.get("identity")
        run.dagger = saved.get("dagger_result")  # the warm start ran when the run began
        if before != made_with:
            was = stamp(before) if before else "none recorded: an older sonogym"
            raise ValueError(
                f"cannot resume {out}: it was trained under another benchmark identity ({was}; "
                f"now {stamp(made_with)}); train it anew with --force"
            )
    resolved = {
        **cfg.to_dict(),
        **_interface(run.adapter),
        "checkpoint_interval": run.ckpt_interval,
        "write_interval": run.write_interval,
        "resumed_from": start,
        "obs_version": get_task(cfg.task).obs_version(cfg.rl.env_kwargs.get("obs_mode")),
        "identity": made_with,
        "versions": _versions(),
    }
    if run.dagger is not None:
        resolved["dagger_result"] = run.dagger
    atomic_write_json(out / "config.json", to_jsonable(resolved))


def _train_loop(
    cfg: TrainConfig, out: Path, run: _Run, start: int, progress: bool,
    log: Callable[[str], None], on_checkpoint: CheckpointCallback | None,
) -> TrainResult:  # fmt: skip
    """Step the envs and the agent from ``start`` to ``cfg.steps``, writing checkpoints (and
    one at Ctrl-C, saying how to resume)."""
    task, algo, steps = cfg.task, cfg.algo, cfg.steps
    agent, adapter, ckpt_dir = run.agent, run.adapter, run.ckpt_dir
    agent.enable_training_mode(True)
    obs, _ = adapter.reset()
    if log is not _quiet:
        _announce(cfg, out, start, log, agent, adapter, obs)
    clock = RunClock(ckpt_dir, start, inherited=_spent_before(cfg.init_from, run.dagger))
    bar = progress_bar(steps, f"{task}/{algo}", initial=start, unit="step", enabled=progress)
    speed = TrainingSpeed(cfg.rl.num_envs)
    done = start
    recent = _EpisodeMeans()
    learning = to_jsonable(cfg.rl.learning)
    try:
        for t in range(start, steps):
            set_log_std_ceiling(run.models["policy"], learning, t)
            if cfg.rl.learning.kl_follows_sigma and getattr(agent, "scheduler", None) is not None:
                agent.scheduler.kl_threshold = kl_threshold_at(cfg.params, cfg.rl.learning, t)
            adapter.update_stats = statistics_update(cfg.rl, t)
            obs = _step(agent, adapter, obs, t, steps, recent, speed)
            done = t + 1
            if done % cfg.params.rollouts == 0:  # an update ran: the figures include one
                bar.set_postfix(**speed.postfix())
            if done % run.ckpt_interval == 0 and done < steps:
                path = save_agent(agent, ckpt_dir / f"agent_{done}.pt")
                clock.record(done, speed)
                if on_checkpoint is not None:
                    on_checkpoint(done, path, recent.pop())
            bar.update(1)
    except KeyboardInterrupt:
        bar.close()
        path = save_agent(agent, ckpt_dir / f"agent_{done}.pt")
        clock.record(done, speed)
        msg = (
            f"interrupted after {done} of {steps} steps; saved {path}. Resume with: sonogym "
            f"train --task {task} --algo {algo} --out {out} --resume"
        )
        log(msg)
        raise TrainingInterrupted(msg) from None
    finally:
        if getattr(agent, "writer", None) is not None:
            agent.writer.flush()
    bar.close()
    final = save_agent(agent, ckpt_dir / f"agent_{steps}.pt")
    clock.record(steps, speed)
    if done > start:
        log(speed.summary())
    if on_checkpoint is not None:
        on_checkpoint(steps, final, recent.pop())
    return TrainResult(out=out, checkpoint=final, steps=steps, speed=speed.figures())


def _step(
    agent, adapter: SkrlEnvAdapter, obs, t: int, steps: int, recent: _EpisodeMeans,
    speed: TrainingSpeed,
):  # fmt: skip
    """One env step of the policy and what the agent records of it (its update, when one is
    due, runs in ``post_interaction``); the next observation. ``speed`` counts the env's and
    the update's wall seconds."""
    agent.pre_interaction(timestep=t, timesteps=steps)
    with torch.no_grad():
        states = adapter.state()  # None unless the critic is privileged
        actions, _ = agent.act(obs, states, timestep=t, timesteps=steps)
        t0 = time.perf_counter()
        next_obs, reward, terminated, truncated, info = adapter.step(actions)
        t1 = time.perf_counter()
        agent.record_transition(
            observations=obs,
            states=states,
            actions=actions,
            rewards=reward,
            next_observations=adapter.final_observations(info, next_obs),
            next_states=adapter.transition_states(info),
            terminated=terminated,
            truncated=truncated,
            infos=info,
            timestep=t,
            timesteps=steps,
        )
        _track_episode_metrics(agent, info)
        recent.add(info)
    t2 = time.perf_counter()
    agent.post_interaction(timestep=t, timesteps=steps)
    speed.add_step(env_s=t1 - t0, update_s=time.perf_counter() - t2)
    return next_obs


class TrainingSpeed:
    """How fast a training process runs and where its wall time goes: env-steps/s (env steps
    of all envs per second of the loop) and the shares of the loop's wall time spent in the
    env's steps (``SkrlEnvAdapter.step``: simulation and observations) and in the learner
    (everything else: the updates, which run in ``post_interaction`` with skrl's TensorBoard
    writes, plus acting, recording, checkpoints and logging).

    The env's share is also the run's speed against the env's own (the same envs stepping
    alone would take the env's seconds only), so ``env_alone_per_s`` estimates the env's own
    env-steps/s at the run's env count and threads. Wall time: on a shared machine other
    tenants slow both parts."""

    def __init__(self, num_envs: int, clock: Callable[[], float] = time.perf_counter) -> None:
        self.num_envs = int(num_envs)
        self.clock = clock
        self.start = clock()
        self.steps = 0  # env steps per env since this process started (or resumed) the run
        self.env_s = 0.0
        self.update_s = 0.0

    def add_step(self, env_s: float, update_s: float) -> None:
        self.steps += 1
        self.env_s += env_s
        self.update_s += update_s

    def figures(self) -> dict[str, float]:
        """{"loop_s", "env_s", "update_s", "env_steps_per_s", "env_alone_per_s",
        "learner_share", "update_share"} since this process started (or resumed) the run
        (shares of the loop's wall time, 0-1)."""
        loop = max(self.clock() - self.start, 1e-9)
        n = self.steps * self.num_envs
        return {
            "loop_s": loop,
            "env_s": self.env_s,
            "update_s": self.update_s,
            "env_steps_per_s": n / loop,
            "env_alone_per_s": n / self.env_s if self.env_s > 0 else 0.0,
            "learner_share": 1.0 - min(self.env_s / loop, 1.0),
            "update_share": min(self.update_s / loop, 1.0),
        }

    def postfix(self) -> dict[str, str]:
        """The progress line's speed entries (``env-steps/s=851, learner=44%``)."""
        f = self.figures()
        return {"env-steps/s": f"{f['env_steps_per_s']:.0f}",
                "learner": f"{100 * f['learner_share']:.0f}%"}  # fmt: skip

    def summary(self) -> str:
        """The line a run ends with: its speed, the env's alone and the learner's share."""
        f = self.figures()
        env_share = 1.0 - f["learner_share"]
        rest = max(f["learner_share"] - f["update_share"], 0.0)
        return (
            f"{f['env_steps_per_s']:.0f} env-steps/s ({self.steps} steps x {self.num_envs} "
            f"envs in {f['loop_s']:.0f} s): the env {100 * env_share:.0f}% of the wall time "
            f"({f['env_alone_per_s']:.0f} env-steps/s alone, so training runs at "
            f"{env_share:.2f}x the env's speed), the learner {100 * f['learner_share']:.0f}% "
            f"(updates {100 * f['update_share']:.0f}%, acting, recording and checkpoints "
            f"{100 * rest:.0f}%)"
        )


class RunClock:
    """CPU and wall seconds a run has spent by each checkpoint, across resumes:
    ``checkpoints/times.json`` = {env steps: {"cpu_s", "wall_s", "loop_s", "env_s",
    "update_s"}} (CPU: this process's, all its threads; what a model card reports as the
    training's cost). A run started from another run's checkpoint (``inherited``: its
    ``init_from``) counts that run's seconds up to the checkpoint too, and a DAgger warm start
    its own: the figures are the policy's cost from random weights. ``loop_s``, ``env_s`` and
    ``update_s`` are this run's own training loop, its env steps and its updates (wall
    seconds, ``TrainingSpeed``): the env-steps/s between two checkpoints is their step
    difference x envs / ``loop_s`` difference, the learner's share 1 - ``env_s`` / ``loop_s``."""

    FILE = "times.json"
    COSTS = ("cpu_s", "wall_s")
    LOOP = ("loop_s", "env_s", "update_s")

    def __init__(self, ckpt_dir: Path, start: int, inherited: dict | None = None) -> None:
        self.path = Path(ckpt_dir) / self.FILE
        self.times = read_times(ckpt_dir)
        zero = {k: float((inherited or {}).get(k) or 0.0) for k in self.COSTS}
        base = self.times.get(start, zero)
        # a resume continues from its checkpoint's totals; later entries were overtaken
        self.times = {t: v for t, v in self.times.items() if t <= start}
        self.cpu0, self.wall0 = time.process_time() - base["cpu_s"], time.time() - base["wall_s"]
        self.loop0 = {k: base.get(k, 0.0) for k in self.LOOP}

    def record(self, step: int, speed: TrainingSpeed | None = None) -> None:
        entry = {
            "cpu_s": round(time.process_time() - self.cpu0, 1),
            "wall_s": round(time.time() - self.wall0, 1),
        }
        if speed is not None:
            f = speed.figures()
            entry.update({k: round(self.loop0[k] + f[k], 1) for k in self.LOOP})
        self.times[step] = entry
        atomic_write_json(self.path, {str(t): v for t, v in sorted(self.times.items())})


def read_times(ckpt_dir: str | Path) -> dict[int, dict[str, float]]:
    """A run's ``checkpoints/times.json`` as {env steps: {"cpu_s", "wall_s"} and, where
    recorded, "loop_s", "env_s", "update_s"} ({} if absent or unreadable)."""
    path = Path(ckpt_dir) / RunClock.FILE
    try:
        raw = json.loads(path.read_text())
        return {int(t): _times_entry(v) for t, v in raw.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def _times_entry(v: dict) -> dict[str, float]:
    entry = {k: float(v[k]) for k in RunClock.COSTS}  # KeyError: not a times.json entry
    entry.update({k: float(v[k]) for k in RunClock.LOOP if k in v})
    return entry


def _spent_before(*sources: dict[str, Any] | None) -> dict[str, float]:
    """CPU and wall seconds the policy cost before the run's first RL step: the ``init_from``
    run's by its checkpoint and the DAgger warm start's (unknown ones count 0)."""
    return {k: sum(float((s or {}).get(k) or 0.0) for s in sources) for k in ("cpu_s", "wall_s")}


class _EpisodeMeans:
    """Sums of the episode metrics of ended episodes, since the last ``pop``."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.count = 0

    def add(self, info: dict[str, Any]) -> None:
        final = info.get("final_info")
        if not final:
            return
        n = len(final["env_ids"])
        for k, v in final.items():
            if k != "env_ids":
                self.sums[k] = self.sums.get(k, 0.0) + float(v.float().sum())
        self.count += n

    def pop(self) -> dict[str, float]:
        out = {k: v / self.count for k, v in self.sums.items()} if self.count else {}
        out["episodes"] = float(self.count)
        self.sums, self.count = {}, 0
        return out


def _models(cfg: TrainConfig, adapter: SkrlEnvAdapter) -> dict:
    task, net, device = cfg.task, cfg.rl.net, cfg.device
    layout, space = adapter.layout, adapter.action_space
    learning = cfg.rl.learning
    state = adapter.state_space
    models = make_models(
        task, layout, space, device, net, learning.init_log_std, learning.init_mean_gain,
        learning.mean_bound_penalty, learning.bounded_mean,
        0 if state is None else math.prod(state.shape),
    )  # fmt: skip
    extra = get_algorithm(cfg.algo).models
    if extra is not None:  # the algorithm's own networks (a cost critic, ...)
        models.update(extra(ModelSetup(task, layout, space, device, net)))
    return models


def warm_start_source(path: str | Path, cfg: TrainConfig) -> dict[str, Any]:
    """Where a run's weights start (``init_from``): an RL checkpoint of a ``sonogym train`` run
    (``RUN/checkpoints/agent_<t>.pt``) or a shipped policy's folder
    (``sonogym.evaluation.pretrained``; ``sonogym train`` takes its name), of the same task,
    network and observation, with its step count and CPU/wall seconds by then (None where
    unknown). Refuses anything else, naming why."""
    path = Path(path)
    if path.is_file():
        run = path.parent.parent
        m = re.fullmatch(RL_RUN.checkpoint_name, path.name)
        if m is None or path.parent.name != "checkpoints" or not (run / "config.json").is_file():
            raise ValueError(
                f"--init-from {path}: not a checkpoint of a sonogym train run; pass "
                f"RUN/checkpoints/{RL_RUN.checkpoint_hint} or a shipped policy's name"
            )
        steps = int(m.group(1))
        spent = read_times(path.parent).get(steps, {})
        cpu_s, wall_s = spent.get("cpu_s"), spent.get("wall_s")
    else:
        run, path = _shipped_policy(path)
        card_path = run / "model_card.json"
        card = read_json(card_path, "shipped policy") if card_path.is_file() else {}
        steps = card.get("steps_per_env")
        cpu_s, wall_s = (
            None if card.get(k) is None else 60.0 * card[k] for k in ("cpu_minutes", "wall_minutes")
        )
    parent = load_train_config(run)
    if parent.task != cfg.task:
        raise ValueError(f"--init-from {path}: a {parent.task} run; this run trains {cfg.task}")

    def obs_mode(c: TrainConfig) -> str:
        return c.rl.env_kwargs.get("obs_mode", get_task(c.task).default_obs_mode)

    for flag, theirs, ours in (
        ("--net", parent.rl.net, cfg.rl.net),
        ("--obs-mode", obs_mode(parent), obs_mode(cfg)),
        ("--obs-downsample", parent.rl.obs_downsample, cfg.rl.obs_downsample),
    ):  # the common mismatches, before the envs are built (warm_start checks the rest)
        if theirs != ours:
            raise ValueError(
                f"--init-from {path}: trained with {flag} {theirs}; this run uses {flag} "
                f"{ours}. Pass {flag} {theirs}"
            )
    return {
        "checkpoint": str(path.resolve()), "run": str(run.resolve()), "steps": steps,
        "cpu_s": cpu_s, "wall_s": wall_s,
    }  # fmt: skip


def _shipped_policy(given: Path) -> tuple[Path, Path]:
    """(folder, weights) of a shipped policy's folder (``sonogym train`` resolves a name)."""
    if given.is_dir() and (given / SHIPPED_WEIGHTS).is_file() and (given / "config.json").is_file():
        return given, given / SHIPPED_WEIGHTS
    raise FileNotFoundError(
        f"--init-from {given}: no such checkpoint file, nor a shipped policy's folder or name "
        "(sonogym eval --pretrained list)"
    )


def _interface(adapter: SkrlEnvAdapter) -> dict[str, Any]:
    """What a policy reads and writes, as ``config.json`` records it: the observation layout
    and the action box (JSON values), and the size of a privileged critic's state (0: none;
    the critic's weights travel with the policy's)."""
    state = adapter.state_space
    return to_jsonable({
        "obs_layout": {"keys": adapter.layout.keys, "shapes": adapter.layout.shapes},
        "action_space": {
            "low": adapter.action_space.low.tolist(),
            "high": adapter.action_space.high.tolist(),
        },
        "privileged_state_size": 0 if state is None else math.prod(state.shape),
    })  # fmt: skip


def warm_start(agent, source: dict[str, Any], adapter: SkrlEnvAdapter) -> None:
    """Load the networks and standardisers of ``source["checkpoint"]`` into ``agent`` (its
    optimiser starts fresh, at the run's learning rate); the run must observe and act exactly
    as the source run did."""
    run = Path(source["run"])
    keys = ("obs_layout", "action_space")
    theirs = read_json(run / "config.json", "`sonogym train` run folder", keys)
    ours = _interface(adapter)  # as this run's config.json will record them
    if theirs["obs_layout"] != ours["obs_layout"]:
        raise ValueError(
            f"--init-from {source['checkpoint']}: that run observed {theirs['obs_layout']}, "
            f"this one observes {ours['obs_layout']}; use the same --obs-mode, --obs-downsample "
            "and env options that shape the observation"
        )
    if theirs["action_space"] != ours["action_space"]:
        raise ValueError(
            f"--init-from {source['checkpoint']}: that run's action box "
            f"{theirs['action_space']} differs from this one's {ours['action_space']}"
        )
    state = read_checkpoint(source["checkpoint"], agent.device)
    for name, module in agent.checkpoint_modules.items():
        if isinstance(module, torch.nn.Module) and name in state:
            _load_warm(module, state[name])


def _load_warm(module: torch.nn.Module, state: dict) -> None:
    """``state`` into ``module``, where only a privileged critic's branch may be missing (it
    then starts at its initial, zero output) or surplus (this run's critic reads no state)."""
    missing, surplus = module.load_state_dict(state, strict=False)
    odd = [k for k in (*missing, *surplus) if not k.startswith("privileged_value.")]
    if odd:
        raise ValueError(f"the warm-start weights do not fit this network: {odd[:5]}")


def save_agent(agent, path: Path) -> Path:
    """Every checkpointed module's state of ``agent`` to ``path``, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {name: m.state_dict() for name, m in agent.checkpoint_modules.items()}
    return atomic_torch_save(state, path)


def load_agent(agent, path: Path) -> None:
    """Restore every checkpointed module of ``agent`` from ``path`` (skrl's ``agent.load``
    unpickles arbitrary objects; ``read_checkpoint`` reads tensors and plain data only)."""
    state = read_checkpoint(path, agent.device)
    missing = sorted(set(agent.checkpoint_modules) - set(state))
    if missing:
        raise ValueError(f"{path} lacks {missing}: was it written by another algorithm?")
    for name, module in agent.checkpoint_modules.items():
        module.load_state_dict(state[name])
    use_multi_tensor_optimizers(agent)


def _announce(cfg: TrainConfig, out: Path, start: int, log, agent, adapter, obs) -> None:
    """The first lines: what will run, an estimate of its time, where the logs go."""
    rl, p = cfg.rl, cfg.params
    updates = max(1, (cfg.steps - start) // p.rollouts)
    log(
        f"{cfg.task}/{cfg.algo} seed {cfg.seed}: {cfg.steps - start} steps x {rl.num_envs} envs "
        f"({updates} updates of {p.rollouts} steps) from step {start}; preset {cfg.preset}: "
        f"net {rl.net}, obs_downsample {rl.obs_downsample}, threads {torch.get_num_threads()}, "
        f"device {cfg.device}"
    )
    step_s, update_s = estimate_costs(cfg, agent, adapter, obs)
    per_update = p.rollouts * step_s + update_s
    log(
        f"estimated {per_update:.1f} s per update ({p.rollouts * step_s:.1f} s rollout, "
        f"{update_s:.1f} s learning), {updates * per_update / 60:.1f} min in all"
    )
    log(f"TensorBoard: tensorboard --logdir {out}; checkpoints in {out / 'checkpoints'}")


def estimate_costs(cfg: TrainConfig, agent, adapter, obs) -> tuple[float, float]:
    """(seconds per env step with the policy acting, seconds of one update's learning), from a
    short measurement: 3 acting steps (after one warm-up) and one forward + backward pass of
    the policy/value on a mini-batch, times the update's mini-batch passes. The env is reset
    to the run's seed afterwards (same first episode as without the estimate)."""
    p = cfg.params
    model = agent.policy
    with torch.random.fork_rng(devices=[]):  # the measurement draws no training randomness
        with torch.no_grad():
            for k in range(4):  # one warm-up step, then three timed
                if k == 1:
                    t0 = time.perf_counter()
                a, _ = agent.act(obs, adapter.state(), timestep=0, timesteps=cfg.steps)
                adapter.unwrapped.step(a)
            step_s = (time.perf_counter() - t0) / 3
        batch = max(1, p.rollouts * cfg.rl.num_envs // p.mini_batches)
        inputs = {"observations": obs[:1].expand(batch, -1).clone()}
        if adapter.state() is not None:  # a privileged critic's input
            inputs["states"] = adapter.state()[:1].expand(batch, -1).clone()
        t0 = time.perf_counter()
        mean, _ = model.act(inputs, role="policy")
        value, _ = model.act(inputs, role="value")
        (mean.sum() + value.sum()).backward()
        model.zero_grad(set_to_none=True)
        update_s = (time.perf_counter() - t0) * getattr(p, "learning_epochs", 1) * p.mini_batches
    adapter.restart()  # the run starts as if unmeasured (staggered again where asked)
    return step_s, update_s


def kl_threshold_at(params: Any, learning: LearningParams, step: int) -> float:
    """The KL-adaptive learning rate's threshold at env step ``step`` (per env): the
    algorithm config's ``kl_threshold``, times (sigma_0 / ceiling)^2 where the task's
    ``learning.kl_follows_sigma`` is set and sigma's ceiling anneals.

    Why: the KL of a fixed change of the Gaussian's mean grows as 1/sigma^2, so with a fixed
    threshold an annealed sigma (surgery: 0.05 -> 0.005) drives the learning rate down ~100x
    to skrl's floor of 1e-6, and the policy freezes with whatever tilt or offset it has then.
    Scaled, the threshold bounds the mean's step per update in action units instead, the same
    at every sigma. Off by default: on the surgery state task it kept the learning rate 3-8x
    higher and made the tilt worse (the reward barely paid for the tilt; the ``cpu`` preset's
    w5 = 50 fixed that)."""
    base = params.kl_threshold
    if not learning.kl_follows_sigma or learning.final_log_std is None:
        return base
    init, final = learning.init_log_std, learning.final_log_std
    ceiling = log_std_ceiling(step, init, final, learning.anneal_steps)
    return base * math.exp(2.0 * (init - ceiling))


def statistics_update(rl: TaskRLConfig, step: int) -> bool:
    """Whether the observation statistics still learn at env step ``step`` (per env): always
    where ``standardize_steps`` is 0, else for its first steps only.

    Why freeze them: they follow the policy's state distribution, and a surgery state run
    that had learned the task collapsed at 68 k steps after its statistics had moved the
    target's standardised depth by 1.2, 0.6 and 0.25 std per 12 k steps while its KL-adaptive
    learning rate, shrinking with sigma, sat at 1e-6: the policy could no longer follow its own
    inputs."""
    frozen_after = rl.learning.standardize_steps
    return frozen_after == 0 or step < frozen_after


def _track_episode_metrics(agent, info: dict[str, Any]) -> None:
    metrics = info.get("final_info")
    if not metrics:
        return
    for k, v in metrics.items():
        if k == "env_ids" or not isinstance(v, torch.Tensor) or v.numel() == 0:
            continue
        agent.track_data(f"Episode / {k}", v.float().mean().item())


def _quiet(msg: str) -> None:
    return None


def _versions() -> dict[str, str]:
    import skrl

    import sonogym

    return {
        "sonogym": getattr(sonogym, "__version__", "unknown"),
        "skrl": skrl.__version__,
        "torch": torch.__version__,
    }
