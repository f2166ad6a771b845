"""Evaluate a trained RL run against the task's expert and a random policy.

``evaluate_run(run_dir, trials)`` rebuilds the run's env (its ``config.json`` env options,
optionally overridden), runs ``trials`` episodes for each controller from the same seeded
starts and returns the task's metrics (mean and std over episodes):

* ``policy``: the run's newest checkpoint, deterministic (the Gaussian's mean action); for a
  ``ppo-sf`` run, through its safety filter (actions with Q_c > threshold become 0);
* ``expert``: the task's expert (navigation, surgery) or heuristic raster (reconstruction),
  from the privileged ``info``, as ``sonogym demo`` runs it;
* ``random``: actions uniform in the env's action box, from a seeded generator.

The table is written to ``<run>/eval.json`` and ``<run>/eval.md``.
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
    trials: int = 100,
    envs: int | None = None,
    seed: int = 1000,
    device: str = "cpu",
    env_overrides: dict[str, Any] | None = None,
    controllers: tuple[str, ...] = CONTROLLERS,
) -> dict[str, dict[str, tuple[float, float]]]:
    """{controller: {metric: (mean, std)}} over ``trials`` episodes each (see module doc)."""
    from sonogym.agents.adapter import SkrlEnvAdapter
    from sonogym.agents.checkpoint import load_policy
    from sonogym.agents.configs import task_config
    from sonogym.agents.train import make_env
    from sonogym.evaluation.demo import DEMO_TASKS

    unknown = sorted(set(controllers) - set(CONTROLLERS))
    if unknown:
        raise ValueError(f"unknown controllers {unknown}; choose from {list(CONTROLLERS)}")
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    run = Path(run)
    model, cfg = load_policy(run, device=device)
    critic = None
    if cfg["algo"] == "ppo-sf":  # the policy acts through its safety filter
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
    low = torch.as_tensor(env.single_action_space.low, device=env.device)
    high = torch.as_tensor(env.single_action_space.high, device=env.device)

    results: dict[str, dict[str, tuple[float, float]]] = {}
    for name in controllers:
        gen = torch.Generator(device="cpu").manual_seed(seed)
        obs, info = env.reset(seed=seed)
        collected: dict[str, list[torch.Tensor]] = {}
        done = 0
        for _ in range(math.ceil(trials / n) * env.episode_length):
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
            if "final_info" in info:
                for k, v in info["final_info"].items():
                    if k != "env_ids":
                        collected.setdefault(k, []).append(v.detach().float().cpu())
                done += len(info["final_info"]["env_ids"])
                if done >= trials:
                    break
        results[name] = {
            k: (float(t[:trials].mean()), float(t[:trials].std()) if trials > 1 else 0.0)
            for k, t in ((k, torch.cat(v)) for k, v in collected.items())
        }
    env.close()
    table = {"task": task, "trials": trials, "seed": seed, "results": results}
    (run / "eval.json").write_text(json.dumps(table, indent=1))
    (run / "eval.md").write_text(format_table(results))
    return results


def format_table(results: dict[str, dict[str, tuple[float, float]]]) -> str:
    """Markdown table: one row per controller, mean ± std per metric."""
    metrics = sorted({k for r in results.values() for k in r})
    lines = ["| controller | " + " | ".join(metrics) + " |", "|---" * (len(metrics) + 1) + "|"]
    for name, r in results.items():
        cells = [f"{r[k][0]:.3f} ± {r[k][1]:.3f}" if k in r else "-" for k in metrics]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
