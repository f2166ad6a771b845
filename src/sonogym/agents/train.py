"""Train a skrl agent on a SonoGym task: ``train(task, algo, ...)`` with algo ``ppo``, ``a2c``,
``ppo-sf`` or ``ppo-lag`` (the task's registry entry lists what it supports).

Writes into ``out/``:

* ``config.json``: the fully resolved run config (task config, algorithm parameters, env
  options, versions), written before training starts;
* TensorBoard event files (skrl's writer: losses, rewards, learning rate; plus the tasks'
  episode metrics under ``Episode / <metric>``);
* ``checkpoints/agent_<t>.pt``: skrl agent checkpoints (policy = value module, optimizer,
  value standardiser) after t env steps per env; ``agent_0.pt`` holds the initial weights, the
  newest one the final policy (skrl also keeps ``best_agent.pt``, best mean return).

The loop is skrl's sequential trainer loop written out, for one reason: with SAME_STEP
autoreset the observation after a truncation is the next episode's first one, so the loop hands
skrl the true final observation (``info["final_obs"]``) as ``next_observations`` for
time-limit bootstrapping, and the reset one as the next step's input.

``resume=True`` continues from the newest checkpoint in ``out/checkpoints`` (weights,
optimizer, standardiser; the envs restart from a fresh reset and the rollout memory is empty).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from sonogym.agents.adapter import SkrlEnvAdapter
from sonogym.agents.checkpoint import latest_checkpoint, read_checkpoint
from sonogym.agents.configs import TaskRLConfig, build_agent, task_config
from sonogym.agents.configs import to_jsonable as _jsonable
from sonogym.agents.networks import make_models
from sonogym.envs.registry import check_algo, make_vec


@dataclass(frozen=True)
class TrainResult:
    out: Path  # run directory
    checkpoint: Path  # the final checkpoint
    steps: int  # env steps per env done in total (including resumed ones)


def make_env(cfg: TaskRLConfig, num_envs: int, device: str | torch.device):
    """The task's batched env (``gymnasium.make_vec``) with ``cfg.env_kwargs`` (device set
    here)."""
    return make_vec(cfg.task, num_envs, **{**cfg.env_kwargs, "device": str(device)})


def train(
    task: str,
    algo: str,
    envs: int | None = None,
    steps: int | None = None,
    seed: int = 0,
    out: str | Path | None = None,
    *,
    patients: tuple | None = None,
    simulator: str | None = None,
    obs_downsample: int | None = None,
    net: str | None = None,
    env_kwargs: dict[str, Any] | None = None,
    device: str = "cpu",
    resume: bool = False,
    checkpoint_interval: int | None = None,
    write_interval: int | None = None,
    progress: bool = True,
) -> TrainResult:
    """Train ``algo`` on ``task`` for ``steps`` env steps per env (default: the paper's).

    Args:
        envs: parallel envs (default 128, paper).
        steps: env steps per env in total, resumed ones included.
        seed: seeds torch and the envs' first reset.
        out: run directory (default ``runs/<task>-<algo>-s<seed>``).
        patients, simulator, obs_downsample, env_kwargs: override the task config's env options.
        net: conv trunk size, "paper" (default) or "small" (the task's registry ``trunks``).
        resume: continue from the newest checkpoint in ``out``; without it an ``out`` that holds
            checkpoints is refused.
        checkpoint_interval, write_interval: in env steps (default: about 10 checkpoints at
            update boundaries; TensorBoard once per update).
        progress: show a tqdm bar with the ETA.
    """
    from skrl.trainers.torch import SequentialTrainerCfg
    from tqdm import tqdm

    check_algo(task, algo)
    base = task_config(task)
    kw = dict(base.env_kwargs)
    kw.update(env_kwargs or {})
    if patients is not None:
        kw["patients"] = tuple(patients)
    if simulator is not None:
        kw["simulator"] = simulator
    cfg = dataclasses.replace(
        base,
        num_envs=envs or base.num_envs,
        timesteps=steps or base.timesteps,
        obs_downsample=obs_downsample or base.obs_downsample,
        net=net or base.net,
        env_kwargs=kw,
    )
    params = cfg.params(algo)
    steps = cfg.timesteps
    out = Path(out or f"runs/{task}-{algo}-s{seed}")
    found = latest_checkpoint(out)
    if found and not resume:
        raise FileExistsError(
            f"{out} already holds checkpoints ({found[0].name}); pass resume=True (--resume) "
            "to continue that run, or choose another output directory"
        )
    if resume and (out / "config.json").exists():
        old = json.loads((out / "config.json").read_text())
        if (old["task"], old["algo"]) != (task, algo):
            raise ValueError(
                f"{out} is a {old['task']}/{old['algo']} run; cannot resume it as {task}/{algo}"
            )
    start = found[1] if (found and resume) else 0
    if start >= steps:
        raise ValueError(f"{out} already has {start} steps >= the requested {steps}")

    torch.manual_seed(seed)
    env = make_env(cfg, cfg.num_envs, device)
    adapter = SkrlEnvAdapter(
        env, cfg.obs_downsample, cfg.obs_scales, seed=seed + start,
        standardize_vectors=cfg.standardize_vectors,
    )  # fmt: skip
    adapter.update_stats = True
    models = make_models(
        task, adapter.layout, adapter.action_space, device, cfg.net, cfg.init_log_std
    )
    if algo == "ppo-sf":
        from sonogym.agents.safety_filter import CostCritic

        models["cost_critic"] = CostCritic(
            task, adapter.layout, adapter.action_space, device, cfg.net
        )
    elif algo == "ppo-lag":
        from sonogym.agents.lagrangian import CostValue

        models["cost_value"] = CostValue(
            task, adapter.layout, adapter.action_space, device, cfg.net
        )
    if checkpoint_interval is None:
        checkpoint_interval = params.rollouts * max(1, round(steps / 10 / params.rollouts))
    if write_interval is None:
        write_interval = params.rollouts
    agent = build_agent(
        cfg,
        algo,
        models,
        adapter.observation_space,
        adapter.action_space,
        cfg.num_envs,
        out,
        device=device,
        write_interval=write_interval,
        checkpoint_interval=checkpoint_interval,
    )
    out.mkdir(parents=True, exist_ok=True)
    resolved = {
        "task": task,
        "algo": algo,
        "seed": seed,
        "num_envs": cfg.num_envs,
        "steps": steps,
        "device": str(device),
        "env_id": cfg.env_id,
        "obs_layout": {"keys": adapter.layout.keys, "shapes": adapter.layout.shapes},
        "action_space": {
            "low": adapter.action_space.low.tolist(),
            "high": adapter.action_space.high.tolist(),
        },
        "checkpoint_interval": checkpoint_interval,
        "write_interval": write_interval,
        "resumed_from": start,
        "task_config": _jsonable(cfg),
        "algo_params": _jsonable(params),
        "versions": _versions(),
    }
    (out / "config.json").write_text(json.dumps(_jsonable(resolved), indent=2))

    if adapter.standardizer is not None:  # saved and restored with the agent
        agent.checkpoint_modules["obs_standardizer"] = adapter.standardizer
    agent.init(trainer_cfg=SequentialTrainerCfg(timesteps=steps))
    if found and resume:
        load_agent(agent, found[0])
    else:
        (out / "checkpoints").mkdir(parents=True, exist_ok=True)
        agent.save(str(out / "checkpoints" / "agent_0.pt"))  # the initial weights
    agent.enable_training_mode(True)
    obs, _ = adapter.reset()
    bar = tqdm(total=steps, initial=start, disable=not progress, unit="step", desc=f"{task}/{algo}")
    for t in range(start, steps):
        agent.pre_interaction(timestep=t, timesteps=steps)
        with torch.no_grad():
            actions, _ = agent.act(obs, None, timestep=t, timesteps=steps)
            next_obs, reward, terminated, truncated, info = adapter.step(actions)
            agent.record_transition(
                observations=obs,
                states=None,
                actions=actions,
                rewards=reward,
                next_observations=adapter.final_observations(info, next_obs),
                next_states=None,
                terminated=terminated,
                truncated=truncated,
                infos=info,
                timestep=t,
                timesteps=steps,
            )
            _track_episode_metrics(agent, info)
        agent.post_interaction(timestep=t, timesteps=steps)
        obs = next_obs
        bar.update(1)
    bar.close()
    final = out / "checkpoints" / f"agent_{steps}.pt"
    if not final.exists():
        final.parent.mkdir(parents=True, exist_ok=True)
        agent.save(str(final))
    if getattr(agent, "writer", None) is not None:
        agent.writer.flush()
    env.close()
    return TrainResult(out=out, checkpoint=final, steps=steps)


def load_agent(agent, path: Path) -> None:
    """Restore every checkpointed module of ``agent`` from ``path`` (skrl's ``agent.load``
    unpickles arbitrary objects; ``read_checkpoint`` reads tensors and plain data only)."""
    state = read_checkpoint(path, agent.device)
    missing = sorted(set(agent.checkpoint_modules) - set(state))
    if missing:
        raise ValueError(f"{path} lacks {missing}: was it written by another algorithm?")
    for name, module in agent.checkpoint_modules.items():
        module.load_state_dict(state[name])


def _track_episode_metrics(agent, info: dict[str, Any]) -> None:
    metrics = info.get("final_info")
    if not metrics:
        return
    for k, v in metrics.items():
        if k == "env_ids" or not isinstance(v, torch.Tensor) or v.numel() == 0:
            continue
        agent.track_data(f"Episode / {k}", v.float().mean().item())


def _versions() -> dict[str, str]:
    import skrl

    import sonogym

    return {
        "sonogym": getattr(sonogym, "__version__", "unknown"),
        "skrl": skrl.__version__,
        "torch": torch.__version__,
    }
