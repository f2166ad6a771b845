"""Evaluate a trained RL run against the task's expert and a random policy.

``evaluate_run(run_dir, trials)`` rebuilds the run's env (its ``config.json`` env options,
optionally overridden), runs ``trials`` episodes for each controller from the same seeded
starts and returns the task's metrics (mean and std over episodes):

* ``policy``: the run's newest checkpoint, deterministic (the Gaussian's mean action); for a
  ``ppo-sf`` run, through its safety filter (actions with Q_c > threshold become 0);
* ``expert``: the task's expert (navigation, surgery) or heuristic raster (reconstruction),
  from the privileged ``info``, as ``sonogym demo`` runs it;
* ``random``: actions uniform in the env's action box, from a seeded generator.

The table is written to ``<run>/eval.json`` and ``<run>/eval.md`` (``eval-<protocol>.*`` for
the out-of-domain protocols), every episode's metrics and trajectory to
``<run>/episodes/<protocol>.npz`` (``sonogym.evaluation.episodes``) and a trajectory figure to
``<run>/trajectories-<protocol>.png``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from sonogym.runs import atomic_write_text, lists_to_tuples, to_jsonable

CONTROLLERS = ("policy", "expert", "random")


def evaluate_run(
    run: str | Path,
    trials: int | None = None,
    envs: int | None = None,
    seed: int | None = None,
    device: str = "cpu",
    env_overrides: dict[str, Any] | None = None,
    controllers: tuple[str, ...] = CONTROLLERS,
    protocol: str | None = None,
    held_out_patients: int = 1,
    plot: bool = True,
    checkpoint: str | Path | None = None,
) -> dict[str, dict[str, tuple[float, float]]]:
    """{controller: {metric: (mean, std)}} over ``trials`` episodes each (see module doc).

    ``checkpoint``: the checkpoint to evaluate (default: the run's newest readable one; an
    unreadable newer one is skipped with a warning naming it).

    ``protocol``: ``idt`` (default), ``odt-sim`` or ``odt-patient``
    (``sonogym.evaluation.protocols``): its test env options override the run's own, and its
    trials (100) and seed (1000) are the defaults. ``env_overrides`` may add other env options
    (not the protocol's). Without a protocol but with overrides the log is named ``custom``.

    Writes ``eval.json`` / ``eval.md`` (``eval-<protocol>.*`` for other than ``idt``), the
    per-episode log ``episodes/<protocol>.npz`` and, with ``plot``, the trajectory figure
    ``trajectories-<protocol>.png``.
    """
    from sonogym.agents.checkpoint import latest_readable_checkpoint, load_policy
    from sonogym.envs.registry import get_task
    from sonogym.evaluation.episodes import load_log, log_path, plot_trajectories, save_log
    from sonogym.evaluation.protocols import PROTOCOL_KEYS
    from sonogym.evaluation.protocols import protocol as get_protocol

    unknown = sorted(set(controllers) - set(CONTROLLERS))
    if unknown:
        raise ValueError(f"unknown controllers {unknown}; choose from {list(CONTROLLERS)}")
    run = Path(run)
    if checkpoint is None:
        found = latest_readable_checkpoint(run) if (run / "config.json").exists() else None
        checkpoint = found[0] if found else None
    _, cfg = load_policy(run, checkpoint, device=device)  # checks the run folder early
    proto = get_protocol(protocol or "idt", held_out_patients)
    trials = proto.trials if trials is None else trials
    seed = proto.seed if seed is None else seed
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    train_env = lists_to_tuples(cfg["task_config"]["env_kwargs"])
    overrides = proto.test_env_overrides(train_env)
    clash = sorted(set(env_overrides or {}) & set(PROTOCOL_KEYS))
    if protocol is not None and clash:
        raise ValueError(
            f"env_overrides {clash} contradict protocol {protocol!r}, which sets them itself"
        )
    overrides.update(env_overrides or {})
    name = protocol or ("custom" if env_overrides else "idt")

    episodes = run_controllers(
        run, trials, envs, seed, device, overrides, controllers, checkpoint=checkpoint
    )
    results = {
        c: {
            k: (float(t.mean()), float(t.std()) if trials > 1 else 0.0)
            for k, t in ((k, torch.from_numpy(v)) for k, v in ep["metrics"].items())
        }
        for c, ep in episodes.items()
    }
    track = get_task(cfg["task"]).track
    meta = {
        "task": cfg["task"],
        "algo": cfg["algo"],
        "run": run.resolve().name,
        "train_seed": cfg["seed"],
        "protocol": name,
        "eval_seed": seed,
        "trials": trials,
        "controllers": list(episodes),
        "checkpoint": Path(checkpoint).name,
        "train_env": cfg["task_config"]["env_kwargs"],
        "test_env": to_jsonable({**train_env, **overrides}),
        "track_columns": list(track.columns),
        "track_units": list(track.units),
    }
    log = save_log(
        log_path(run, name),
        meta,
        {c: ep["metrics"] for c, ep in episodes.items()},
        {c: ep["track"] for c, ep in episodes.items()},
    )
    if plot:
        plot_trajectories(load_log(log), run / f"trajectories-{name}.png")
    stem = "eval" if name == "idt" else f"eval-{name}"
    table = {
        "task": cfg["task"],
        "trials": trials,
        "seed": seed,
        "protocol": name,
        "env_overrides": to_jsonable(overrides),
        "results": results,
    }
    atomic_write_text(run / f"{stem}.json", json.dumps(table, indent=1))
    atomic_write_text(run / f"{stem}.md", format_table(results))
    return results


def controller_policy(
    name: str, env, task: str, run: str | Path, seed: int, device: str = "cpu", checkpoint=None
):
    """The ``Policy`` of controller ``name`` in ``env``: the run's trained policy (its
    ``checkpoint``, default the newest readable), the task's expert (or heuristic), or uniform
    random actions from ``seed``."""
    if name == "policy":
        from sonogym.agents.checkpoint import rl_policy

        return rl_policy(run, env, checkpoint, device=device)
    if name == "expert":
        from sonogym.envs.policy import ExpertPolicy
        from sonogym.envs.registry import get_task

        return ExpertPolicy(env, get_task(task).expert)
    if name == "random":
        from sonogym.envs.policy import RandomPolicy

        return RandomPolicy(env, seed)
    raise ValueError(f"unknown controller {name!r}; choose from {list(CONTROLLERS)}")


def run_controllers(
    run: str | Path,
    trials: int,
    envs: int | None = None,
    seed: int = 1000,
    device: str = "cpu",
    env_overrides: dict[str, Any] | None = None,
    controllers: tuple[str, ...] = CONTROLLERS,
    checkpoint: str | Path | None = None,
) -> dict[str, dict[str, Any]]:
    """Run ``trials`` episodes per controller in the run's env (with ``env_overrides``), all
    from the same seeded starts: {controller: {"metrics": {metric: (trials,) array},
    "track": (trials, T + 1, D) array}} (see ``episodes.run_episodes``). Nothing is written."""
    from sonogym.agents.checkpoint import load_policy
    from sonogym.agents.configs import task_config
    from sonogym.agents.train import make_env
    from sonogym.evaluation.episodes import run_episodes

    _, cfg = load_policy(run, checkpoint, device=device)  # checks the run folder early
    task = cfg["task"]
    env_kwargs = {**lists_to_tuples(cfg["task_config"]["env_kwargs"]), **(env_overrides or {})}
    env = make_env(task_config(task, env_kwargs=env_kwargs), min(trials, envs or 16), device)
    out = {
        name: run_episodes(
            env,
            controller_policy(name, env, task, run, seed, device, checkpoint),
            trials,
            seed,
            task,
        )
        for name in controllers
    }
    env.close()
    return out


def format_table(results: dict[str, dict[str, tuple[float, float]]]) -> str:
    """Markdown table: one row per controller, mean ± std per metric."""
    metrics = sorted({k for r in results.values() for k in r})
    lines = ["| controller | " + " | ".join(metrics) + " |", "|---" * (len(metrics) + 1) + "|"]
    for name, r in results.items():
        cells = [f"{r[k][0]:.3f} ± {r[k][1]:.3f}" if k in r else "-" for k in metrics]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
