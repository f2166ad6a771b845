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
import math
from pathlib import Path
from typing import Any

import torch

CONTROLLERS = ("policy", "expert", "random")


def _tuples(x: Any) -> Any:
    if isinstance(x, list):
        return tuple(_tuples(v) for v in x)
    if isinstance(x, dict):
        return {k: _tuples(v) for k, v in x.items()}
    return x


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
) -> dict[str, dict[str, tuple[float, float]]]:
    """{controller: {metric: (mean, std)}} over ``trials`` episodes each (see module doc).

    ``protocol``: ``idt`` (default), ``odt-sim`` or ``odt-patient``
    (``sonogym.evaluation.protocols``): its test env options override the run's own, and its
    trials (100) and seed (1000) are the defaults. ``env_overrides`` may add other env options
    (not the protocol's). Without a protocol but with overrides the log is named ``custom``.

    Writes ``eval.json`` / ``eval.md`` (``eval-<protocol>.*`` for other than ``idt``), the
    per-episode log ``episodes/<protocol>.npz`` and, with ``plot``, the trajectory figure
    ``trajectories-<protocol>.png``.
    """
    from sonogym.agents.checkpoint import load_policy
    from sonogym.agents.train import latest_checkpoint
    from sonogym.evaluation.episodes import TRACKS, load_log, log_path, plot_trajectories, save_log
    from sonogym.evaluation.protocols import PROTOCOL_KEYS
    from sonogym.evaluation.protocols import protocol as get_protocol

    unknown = sorted(set(controllers) - set(CONTROLLERS))
    if unknown:
        raise ValueError(f"unknown controllers {unknown}; choose from {list(CONTROLLERS)}")
    run = Path(run)
    _, cfg = load_policy(run, device=device)  # checks the run folder early
    proto = get_protocol(protocol or "idt", held_out_patients)
    trials = proto.trials if trials is None else trials
    seed = proto.seed if seed is None else seed
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    train_env = _tuples(cfg["task_config"]["env_kwargs"])
    overrides = proto.test_env_overrides(train_env)
    clash = sorted(set(env_overrides or {}) & set(PROTOCOL_KEYS))
    if protocol is not None and clash:
        raise ValueError(
            f"env_overrides {clash} contradict protocol {protocol!r}, which sets them itself"
        )
    overrides.update(env_overrides or {})
    name = protocol or ("custom" if env_overrides else "idt")

    episodes = rollout(run, trials, envs, seed, device, overrides, controllers)
    results = {
        c: {
            k: (float(t.mean()), float(t.std()) if trials > 1 else 0.0)
            for k, t in ((k, torch.from_numpy(v)) for k, v in ep["metrics"].items())
        }
        for c, ep in episodes.items()
    }
    track = TRACKS[cfg["task"]]
    meta = {
        "task": cfg["task"],
        "algo": cfg["algo"],
        "run": run.resolve().name,
        "train_seed": cfg["seed"],
        "protocol": name,
        "eval_seed": seed,
        "trials": trials,
        "controllers": list(episodes),
        "checkpoint": latest_checkpoint(run)[0].name,
        "train_env": cfg["task_config"]["env_kwargs"],
        "test_env": _jsonable({**train_env, **overrides}),
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
        "env_overrides": _jsonable(overrides),
        "results": results,
    }
    (run / f"{stem}.json").write_text(json.dumps(table, indent=1))
    (run / f"{stem}.md").write_text(format_table(results))
    return results


def rollout(
    run: str | Path,
    trials: int,
    envs: int | None = None,
    seed: int = 1000,
    device: str = "cpu",
    env_overrides: dict[str, Any] | None = None,
    controllers: tuple[str, ...] = CONTROLLERS,
) -> dict[str, dict[str, Any]]:
    """Run ``trials`` episodes per controller in the run's env (with ``env_overrides``), all
    from the same seeded starts: {controller: {"metrics": {metric: (trials,) array},
    "track": (trials, T + 1, D) array}} (see ``episodes.TRACKS``). Nothing is written."""
    from sonogym.agents.adapter import SkrlEnvAdapter
    from sonogym.agents.checkpoint import load_policy
    from sonogym.agents.configs import task_config
    from sonogym.agents.train import make_env
    from sonogym.evaluation.demo import DEMO_TASKS
    from sonogym.evaluation.episodes import TRACKS, current_info

    run = Path(run)
    model, cfg = load_policy(run, device=device)
    critic = None
    if cfg["algo"] == "ppo-sf" and "policy" in controllers:  # acts through its safety filter
        from sonogym.agents.checkpoint import load_cost_critic
        from sonogym.agents.safety_filter import filter_actions

        critic, threshold = load_cost_critic(run, device=device)
    task = cfg["task"]
    tc = cfg["task_config"]
    env_kwargs = {**_tuples(tc["env_kwargs"]), **(env_overrides or {})}
    n = min(trials, envs or 16)
    env = make_env(task_config(task, env_kwargs=env_kwargs), n, device)
    adapter = SkrlEnvAdapter(env, tc["obs_downsample"], tc["obs_scales"])
    demo = DEMO_TASKS[task]
    track = TRACKS[task]
    low = torch.as_tensor(env.single_action_space.low, device=env.device)
    high = torch.as_tensor(env.single_action_space.high, device=env.device)
    T = env.episode_length
    batches = math.ceil(trials / n)

    out: dict[str, dict[str, Any]] = {}
    for name in controllers:
        gen = torch.Generator(device="cpu").manual_seed(seed)
        obs, info = env.reset(seed=seed)
        collected: dict[str, list[torch.Tensor]] = {}
        paths = torch.zeros(batches * n, T + 1, len(track.columns))
        for b in range(batches):
            rows = slice(b * n, (b + 1) * n)
            paths[rows, 0] = track.fn(env, info if b == 0 else current_info(env)).float().cpu()
            for t in range(T):
                with torch.no_grad():
                    if name == "policy":
                        x = adapter.flatten(obs)
                        action = model.act({"observations": x}, role="policy")[1]["mean_actions"]
                        if critic is not None:
                            action, _ = filter_actions(critic, x, action, threshold)
                    elif name == "expert":
                        action = demo.expert(env, info)
                    else:
                        u = torch.rand(n, *low.shape, generator=gen).to(env.device)
                        action = low + (high - low) * u
                obs, _, _, _, info = env.step(action)
                paths[rows, t + 1] = track.fn(env, info).float().cpu()
                final = info.get("final_info")
                if final is not None:
                    if t != T - 1 or len(final["env_ids"]) != n:
                        raise RuntimeError(
                            f"{task}: episodes ended out of step (step {t + 1} of {T}, "
                            f"{len(final['env_ids'])} of {n} envs); the log assumes fixed-length"
                            " episodes"
                        )
                    order = torch.argsort(final["env_ids"].cpu())
                    for k, v in final.items():
                        if k != "env_ids":
                            collected.setdefault(k, []).append(v.detach().float().cpu()[order])
        out[name] = {
            "metrics": {k: torch.cat(v)[:trials].numpy() for k, v in collected.items()},
            "track": paths[:trials].numpy(),
        }
    env.close()
    return out


def _jsonable(x: Any) -> Any:
    from sonogym.agents.configs import to_jsonable

    return to_jsonable(x)


def format_table(results: dict[str, dict[str, tuple[float, float]]]) -> str:
    """Markdown table: one row per controller, mean ± std per metric."""
    metrics = sorted({k for r in results.values() for k in r})
    lines = ["| controller | " + " | ".join(metrics) + " |", "|---" * (len(metrics) + 1) + "|"]
    for name, r in results.items():
        cells = [f"{r[k][0]:.3f} ± {r[k][1]:.3f}" if k in r else "-" for k in metrics]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
