"""A trained run folder, RL (``sonogym train``) or imitation learning (``sonogym il-train``),
seen the same way by evaluation, plots and reports: its task, algorithm, seed, the env options
it was trained on, its checkpoints and its policy acting in an env.

The folder is read through ``sonogym.runs.RunFolder``; its ``RunKind`` (RL:
``agents.checkpoint.RL_RUN``; IL: ``imitation.run.IL_RUN``, whose config.json says ``kind``
"sonogym-il-run") checks its config.json and reads its checkpoints. RL runs' config.json is
``TrainConfig.to_dict`` plus layout fields; IL runs' holds the task and env options of the
dataset it learned from (for an IL run, the training env is the one the expert dataset was
recorded in, without the data collection's wider starts).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sonogym.runs import RunFolder, RunKind, lists_to_tuples, open_run


def run_kinds() -> tuple[RunKind, ...]:
    """The kinds of training run evaluation reads (imported here, not at module import: the
    RL side loads skrl)."""
    from sonogym.agents.checkpoint import RL_RUN
    from sonogym.imitation.run import IL_RUN

    return RL_RUN, IL_RUN


@dataclass(frozen=True)
class TrainedRun:
    path: Path
    kind: str  # "rl" or "il"
    task: str
    algo: str  # an RL algorithm's name (ppo, ...); an imitation policy's algo (act, dp)
    seed: int
    env_kwargs: dict[str, Any]  # env options of training (tuples)
    config: dict[str, Any]  # the whole config.json

    @property
    def num_envs(self) -> int | None:
        """Parallel envs of RL training (None for IL)."""
        return self.config.get("num_envs")

    @property
    def folder(self) -> RunFolder:
        return RunFolder(self.path, next(k for k in run_kinds() if k.name == self.kind))

    def evaluation_env_kwargs(self, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
        """The env options this policy is tested with: training's, ``overrides`` on top, and
        images as simulated (training's per-episode imaging randomisation stays in training)."""
        return {**self.env_kwargs, **(overrides or {}), "imaging_randomization": False}


def load_run(run: str | Path) -> TrainedRun:
    """The run folder's ``TrainedRun``, with a clear error for a folder that is not one."""
    folder = open_run(run, run_kinds())
    cfg = folder.config()  # checked as evaluation needs it
    env = lists_to_tuples(folder.kind.env_kwargs(cfg))
    return TrainedRun(folder.path, folder.kind.name, cfg["task"], cfg["algo"],
                      int(cfg.get("seed", 0)), env, cfg)  # fmt: skip


def newest_checkpoint(run: TrainedRun, warn=None) -> Path:
    """The checkpoint evaluation uses by default: the newest readable one."""
    return run.folder.require_checkpoint(warn=warn).path


def run_policy(
    run: TrainedRun, env, checkpoint: str | Path | None = None, device="cpu",
    controller: str = "policy", settings: dict[str, Any] | None = None,
):  # fmt: skip
    """The run's trained ``Policy`` acting in ``env`` (an env of its task): an RL policy reads
    the env's observations through its adapter and acts as its algorithm does (evaluation
    controller ``controller``, test-time ``settings``: ``agents.checkpoint.rl_policy``), an IL
    policy reads them through the task's dataset features."""
    if run.kind == "il":
        from sonogym.imitation.policy import load_il_policy
        from sonogym.imitation.record import obs_to_features

        return load_il_policy(run.path, obs_to_features(run.task), device, checkpoint)
    from sonogym.agents.checkpoint import rl_policy

    return rl_policy(run.path, env, checkpoint, device=device, controller=controller,
                     settings=settings)  # fmt: skip
