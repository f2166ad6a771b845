"""IL run folders: policy factory, atomic checkpoints, and loading a trained model back.

A run folder (written by ``sonogym.imitation.train.train_il``)::

    RUN/config.json                       resolved config: policy name and config, training
                                          settings, dataset path and features, stats used
    RUN/checkpoints/step_000005000.pt     {"model", "optimizer", "scheduler", "step", "rng"}:
                                          plain state_dicts, loadable with weights_only=True
    RUN/tb/                               TensorBoard scalars

Every file is written to a temp name and renamed, so a killed run never leaves half a file.
"""

from __future__ import annotations

import dataclasses
import re
import warnings
from pathlib import Path
from typing import Any

import torch

from sonogym.envs.registry import check_task_name
from sonogym.imitation import act, diffusion
from sonogym.imitation.processor import PolicyFeatures
from sonogym.runs import (
    CheckpointError,
    atomic_torch_save,
    atomic_write_json,
    load_weights,
    read_json,
)

POLICIES = ("act", "diffusion")
RUN_KIND = "sonogym-il-run"
_CKPT = re.compile(r"step_(\d+)\.pt$")


def make_config(policy: str, preset: str = "cpu", **overrides):
    """The ``paper`` or ``cpu`` preset config of ``policy`` ("act" or "diffusion")."""
    cls = {"act": act.ACTConfig, "diffusion": diffusion.DiffusionConfig}.get(policy)
    if cls is None:
        raise ValueError(f"unknown policy {policy!r}; choose one of {POLICIES}")
    if preset not in ("paper", "cpu"):
        raise ValueError(f"unknown preset {preset!r}; choose 'paper' or 'cpu'")
    return getattr(cls, preset)(**overrides)


def policy_name(config) -> str:
    if isinstance(config, act.ACTConfig):
        return "act"
    if isinstance(config, diffusion.DiffusionConfig):
        return "diffusion"
    raise TypeError(f"not an IL policy config: {type(config).__name__}")


def make_policy(config, features: PolicyFeatures, stats) -> torch.nn.Module:
    """ACTPolicy or DiffusionPolicy for ``config`` over ``features``, normalised by ``stats``."""
    if isinstance(config, act.ACTConfig):
        return act.ACTPolicy(config, features, stats)
    if isinstance(config, diffusion.DiffusionConfig):
        return diffusion.DiffusionPolicy(config, features, stats)
    raise TypeError(f"not an IL policy config: {type(config).__name__}")


def config_from_dict(policy: str, d: dict[str, Any]):
    if policy == "act":
        return act.config_from_dict(d)
    if policy == "diffusion":
        return diffusion.config_from_dict(d)
    raise ValueError(f"unknown policy {policy!r} in a run config; known: {POLICIES}")


def checkpoints(run: str | Path) -> list[tuple[int, Path]]:
    """(step, path) of the run's checkpoints, oldest first."""
    found = []
    for p in (Path(run) / "checkpoints").glob("step_*.pt"):
        m = _CKPT.search(p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found)


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


def newest_readable_checkpoint(
    run: str | Path, device: str | torch.device = "cpu", warn=None
) -> tuple[Path, dict[str, Any]] | None:
    """(path, state) of the run's newest checkpoint that reads, or None; each unreadable newer
    one (a save killed half-way, a corrupt file) is skipped with a warning naming it (``warn``:
    a callable taking the message; default ``warnings.warn``)."""
    for _, path in reversed(checkpoints(run)):
        try:
            return path, load_checkpoint(path, device)
        except (CheckpointError, OSError) as e:
            (warn or (lambda m: warnings.warn(m, stacklevel=3)))(
                f"skipping unreadable checkpoint: {e}"
            )
    return None


def write_run_config(run: Path, cfg: dict[str, Any]) -> None:
    atomic_write_json(Path(run) / "config.json", {"kind": RUN_KIND, **cfg}, indent=4)


#: keys every IL run's config.json has (what resume and evaluation read)
RUN_CONFIG_KEYS = ("kind", "policy", "policy_config", "train", "features", "stats")


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


def load_model(
    run: str | Path,
    device: str | torch.device = "cpu",
    checkpoint: str | Path | None = None,
    **config_overrides,
) -> tuple[torch.nn.Module, dict[str, Any]]:
    """(model in eval mode, run config) from a run folder, newest checkpoint unless given.

    ``config_overrides`` change inference-only settings (``temporal_ensemble_coeff``,
    ``n_action_steps``, ``scheduler``, ``num_inference_steps``); the dataset is not needed
    (the normalisation statistics come from config.json and the checkpoint).
    """
    cfg = read_run_config(run)
    config = config_from_dict(cfg["policy"], cfg["policy_config"])
    if config_overrides:
        config = dataclasses.replace(config, **config_overrides)
    features = PolicyFeatures.from_dict(cfg["features"])
    stats = {
        k: {s: torch.tensor(v, dtype=torch.float32) for s, v in d.items()}
        for k, d in cfg["stats"].items()
    }
    model = make_policy(config, features, stats).to(device)
    if checkpoint is None:
        found = newest_readable_checkpoint(run, device)
        if found is None:
            raise FileNotFoundError(f"no readable checkpoints/step_*.pt in {run}")
        state = found[1]
    else:
        state = load_checkpoint(checkpoint, device)
    model.load_state_dict(state["model"])
    model.eval()
    return model, cfg
