"""A trained run folder, RL (``sonogym train``) or imitation learning (``sonogym il-train``),
seen the same way by evaluation, plots and reports: its task, algorithm, seed, the env options
it was trained on, and its policy acting in an env.

RL runs' ``config.json`` is ``TrainConfig.to_dict`` plus layout fields; IL runs' has
``kind`` "sonogym-il-run" and the task and env options of the dataset it learned from (for an
IL run, the training env is the one the expert dataset was recorded in, without the data
collection's wider starts).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sonogym.envs.registry import check_task_name
from sonogym.runs import lists_to_tuples, read_json

IL_KIND = "sonogym-il-run"


@dataclass(frozen=True)
class TrainedRun:
    path: Path
    kind: str  # "rl" or "il"
    task: str
    algo: str  # ppo, a2c, ppo-sf, ppo-lag; act, dp
    seed: int
    env_kwargs: dict[str, Any]  # env options of training (tuples)
    config: dict[str, Any]  # the whole config.json

    @property
    def num_envs(self) -> int | None:
        """Parallel envs of RL training (None for IL)."""
        return self.config.get("num_envs")


def load_run(run: str | Path) -> TrainedRun:
    """The run folder's ``TrainedRun``, with a clear error for a folder that is not one."""
    run = Path(run)
    cfg = read_json(run / "config.json", "`sonogym train` / `il-train` run folder", ("task",))
    if cfg.get("kind") == IL_KIND:
        if not cfg.get("task"):
            raise ValueError(
                f"{run} was trained on a dataset not recorded by sonogym (no task known); "
                "evaluate it with load_il_policy and your own env"
            )
        check_task_name(cfg["task"], run / "config.json")  # it names files (eval, plots)
        env = lists_to_tuples(cfg.get("env_kwargs", {}))
        _check_il_config(run / "config.json", cfg, env)
        return TrainedRun(run, "il", cfg["task"], cfg["algo"], int(cfg.get("seed", 0)), env,
                          cfg)  # fmt: skip
    from sonogym.agents.checkpoint import run_config

    cfg = run_config(run)  # checks the RL keys
    env = cfg["task_config"]["env_kwargs"]
    return TrainedRun(run, "rl", cfg["task"], cfg["algo"], int(cfg["seed"]),
                      lists_to_tuples(env), cfg)  # fmt: skip


def _check_il_config(path: Path, cfg: dict[str, Any], env: Any) -> None:
    """An IL run's config.json as evaluation reads it, checked before any env is built: its
    task (known, and the one whose features the policy was trained on), algorithm, seed and
    env options; a hand-edited or foreign one is named."""
    from sonogym.envs.registry import env_config
    from sonogym.imitation.processor import PolicyFeatures
    from sonogym.imitation.record import check_task_features
    from sonogym.imitation.run import read_run_config

    fix = "restore the config.json the run wrote, or retrain the run"
    read_run_config(path.parent)  # its kind and keys
    seed = cfg.get("seed", 0)
    if cfg.get("algo") not in ("act", "dp") or isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(
            f"{path}: algo {cfg.get('algo')!r} (act or dp) or seed {seed!r} (an integer) is not "
            f"an IL run's; {fix}"
        )
    try:
        if not isinstance(env, dict):
            raise ValueError(f"env_kwargs must be an object, got {env!r}")
        env_config(cfg["task"], env)
        features = PolicyFeatures.from_dict(cfg["features"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}; {fix}") from None
    check_task_features(cfg["task"], features, str(path))


def newest_checkpoint(run: TrainedRun, warn=None) -> Path:
    """The checkpoint evaluation uses by default: the newest readable one."""
    if run.kind == "il":
        from sonogym.imitation.run import newest_readable_checkpoint

        found = newest_readable_checkpoint(run.path, warn=warn)
        if found is None:
            raise FileNotFoundError(f"no readable checkpoints/step_*.pt in {run.path}")
        return found[0]
    from sonogym.agents.checkpoint import latest_readable_checkpoint

    found = latest_readable_checkpoint(run.path, warn)
    if found is None:
        raise FileNotFoundError(f"no readable checkpoints/agent_<t>.pt in {run.path}")
    return found[0]


def run_policy(run: TrainedRun, env, checkpoint: str | Path | None = None, device="cpu"):
    """The run's trained ``Policy`` acting in ``env`` (an env of its task)."""
    if run.kind == "il":
        from sonogym.imitation.policy import load_il_policy
        from sonogym.imitation.record import obs_to_features

        return load_il_policy(run.path, obs_to_features(run.task), device, checkpoint)
    from sonogym.agents.checkpoint import rl_policy

    return rl_policy(run.path, env, checkpoint, device=device)
