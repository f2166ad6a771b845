"""IL run folders: atomic checkpoints, the run config, and loading a trained model back.

A run folder (written by ``sonogym.imitation.train.train_il``)::

    RUN/config.json                       resolved config: policy name and config, training
                                          settings, dataset path and features, stats used
    RUN/checkpoints/step_000005000.pt     {"model", "optimizer", "scheduler", "step", "rng"}:
                                          plain state_dicts, loadable with weights_only=True
    RUN/tb/                               TensorBoard scalars

Every file is written to a temp name and renamed, so a killed run never leaves half a file.
``IL_RUN`` is how ``sonogym.runs.RunFolder`` reads such a folder (checkpoints, config).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from sonogym.envs.registry import check_task_name
from sonogym.imitation.policies.base import ILModel
from sonogym.imitation.policies.registry import get_policy, policy_for_algo, policy_names
from sonogym.imitation.processor import PolicyFeatures
from sonogym.runs import (
    CheckpointError,
    RunFolder,
    RunKind,
    atomic_torch_save,
    atomic_write_json,
    lists_to_tuples,
    load_weights,
    read_json,
)


def save_checkpoint(run: Path, step: int, state: dict[str, Any]) -> Path:
    """The run's checkpoint after ``step`` optimiser steps, written atomically."""
    return atomic_torch_save(state, Path(run) / "checkpoints" / f"step_{step:09d}.pt")


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    """A checkpoint's dict, loaded with ``weights_only=True`` (tensors and plain containers);
    a missing file raises ``FileNotFoundError``, an empty, truncated or foreign one
    ``CheckpointError`` naming it."""
    path = Path(path)
    state = load_weights(path, device, "IL checkpoint")
    if not isinstance(state, dict) or "model" not in state or "step" not in state:
        raise CheckpointError(f"{path} is not an IL checkpoint (no 'model' and 'step')")
    return state


#: config.json's "kind" of an IL run
RUN_KIND = "sonogym-il-run"
#: keys every IL run's config.json has (what resume and evaluation read)
RUN_CONFIG_KEYS = ("kind", "policy", "policy_config", "train", "features", "stats")


def write_run_config(run: Path, cfg: dict[str, Any]) -> None:
    atomic_write_json(Path(run) / "config.json", {"kind": RUN_KIND, **cfg}, indent=4)


def read_run_config(run: str | Path) -> dict[str, Any]:
    """An IL run's ``config.json``, with a clear error naming the file if it is missing,
    malformed, incomplete or not an IL run's."""
    path = Path(run) / "config.json"
    cfg = read_json(path, "`sonogym il-train` run folder")
    if cfg.get("kind") != RUN_KIND:
        raise ValueError(f"{path} is not an IL run config (kind {cfg.get('kind')!r})")
    missing = [k for k in RUN_CONFIG_KEYS if k not in cfg]
    if missing:
        raise ValueError(f"{path} lacks {missing}: it was not written by `sonogym il-train`")
    if cfg.get("task") is not None:  # None: a dataset sonogym did not record
        check_task_name(cfg["task"], path)
    return cfg


def read_evaluable_config(run: str | Path) -> dict[str, Any]:
    """An IL run's config.json checked as evaluation reads it, before any env is built: its
    task (known, and the one whose features the policy was trained on), algorithm, seed and
    env options; a hand-edited or foreign one is named."""
    from sonogym.envs.registry import env_config
    from sonogym.imitation.record import check_task_features

    run = Path(run)
    path = run / "config.json"
    cfg = read_run_config(run)  # its kind and keys
    if not cfg.get("task"):
        raise ValueError(
            f"{run} was trained on a dataset not recorded by sonogym (no task known); "
            "evaluate it with load_il_policy and your own env"
        )
    fix = "restore the config.json the run wrote, or retrain the run"
    seed = cfg.get("seed", 0)
    if (
        policy_for_algo(cfg.get("algo")) is None
        or isinstance(seed, bool)
        or not isinstance(seed, int)
    ):
        algos = " or ".join(get_policy(name).algo for name in policy_names())
        raise ValueError(
            f"{path}: algo {cfg.get('algo')!r} ({algos}) or seed {seed!r} (an integer) is not "
            f"an IL run's; {fix}"
        )
    env = lists_to_tuples(cfg.get("env_kwargs", {}))
    try:
        if not isinstance(env, dict):
            raise ValueError(f"env_kwargs must be an object, got {env!r}")
        env_config(cfg["task"], env)
        features = PolicyFeatures.from_dict(cfg["features"])
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: {e}; {fix}") from None
    check_task_features(cfg["task"], features, str(path))
    return cfg


IL_RUN = RunKind(
    name="il",
    command="sonogym il-train",
    marker=RUN_KIND,
    checkpoint_name=r"step_(\d+)\.pt",
    checkpoint_hint="step_*.pt",
    read_checkpoint=load_checkpoint,
    read_config=read_evaluable_config,
    env_kwargs_key=("env_kwargs",),
)


def load_model(
    run: str | Path,
    device: str | torch.device = "cpu",
    checkpoint: str | Path | None = None,
    **config_overrides,
) -> tuple[ILModel, dict[str, Any]]:
    """(model in eval mode, run config) from a run folder, newest checkpoint unless given.

    ``config_overrides`` change inference-only settings (``temporal_ensemble_coeff``,
    ``n_action_steps``, ``scheduler``, ``num_inference_steps``); the dataset is not needed
    (the normalisation statistics come from config.json and the checkpoint).
    """
    cfg = read_run_config(run)
    spec = get_policy(cfg["policy"])
    config = spec.config_cls.from_dict(cfg["policy_config"])
    if config_overrides:
        config = dataclasses.replace(config, **config_overrides)
    features = PolicyFeatures.from_dict(cfg["features"])
    stats = {
        k: {s: torch.tensor(v, dtype=torch.float32) for s, v in d.items()}
        for k, d in cfg["stats"].items()
    }
    model = spec.model_cls(config, features, stats).to(device)
    if checkpoint is None:
        state = RunFolder(run, IL_RUN).require_checkpoint(device).state
    else:
        state = load_checkpoint(checkpoint, device)
    model.load_state_dict(state["model"])
    model.eval()
    return model, cfg
