"""A task's expert datasets: the records a task's dataset module is made of (``DatasetSpec``,
``Feature``, ``DatasetRecipe``) and ``dataset_spec(task)``, which loads that module.

Each task with expert datasets has a dataset module (``sonogym.tasks.<task>.dataset``) holding
its ``DatasetSpec``: how the env's observation maps to LeRobot features, the task string, the
control rate, which expert episodes are kept, and the paper's recording recipes. The task's
``TaskSpec.dataset`` names the module by entry point (``"module:ATTRIBUTE"``), so the env
package imports nothing from it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from typing import Any, Literal

import torch


@dataclass(frozen=True)
class Feature:
    """One LeRobot dataset feature taken from the env: ``fn(obs, info)`` -> (N, *shape).

    ``dtype`` "image" (``shape`` (C, H, W) as the env gives it, float in [0, 1]; datasets store
    LeRobot's (H, W, C)) or "float32"; ``names`` per LeRobot's ``info.json``."""

    key: str
    dtype: Literal["image", "float32"]
    shape: tuple[int, ...]
    names: tuple[str, ...] | None
    fn: Callable[[Any, dict[str, Any]], torch.Tensor]


@dataclass(frozen=True)
class DatasetRecipe:
    """How one of the paper's expert datasets is recorded: its name (``sonogym record
    --recipe``), default episode count and the env options it records with (simulator, nets,
    patients, start randomisation)."""

    name: str
    episodes: int
    env_kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class DatasetSpec:
    """How a task's expert datasets look (LeRobotDataset v3.0, ``sonogym.imitation``).

    ``features`` map the env's observation to dataset keys (the action is added as
    ``action``); ``instruction`` is LeRobot's task string; ``fps`` the control rate the
    timestamps count (steps per second); ``success(metrics)`` -> (N,) bool keeps the expert
    episodes worth imitating (a failed one is counted, not written)."""

    features: tuple[Feature, ...]
    instruction: str
    robot_type: str
    fps: int
    recipes: tuple[DatasetRecipe, ...]
    success: Callable[[dict[str, torch.Tensor]], torch.Tensor]

    def recipe(self, name: str) -> DatasetRecipe:
        for r in self.recipes:
            if r.name == name:
                return r
        raise ValueError(
            f"unknown dataset recipe {name!r}; choose from {[r.name for r in self.recipes]}"
        )


@cache
def dataset_spec(task: str) -> DatasetSpec:
    """The ``DatasetSpec`` of ``task`` (or of its Gymnasium id), from the module its
    ``TaskSpec.dataset`` names; a task without one is refused, naming those with one."""
    from sonogym.envs.registry import TASKS, get_task
    from sonogym.envs.spec import load_entry_point

    spec = get_task(task)
    if spec.dataset is None:
        with_data = ", ".join(t.name for t in TASKS.values() if t.dataset is not None)
        raise ValueError(f"{task} has no expert datasets (tasks with one: {with_data})")
    return load_entry_point(spec.dataset, DatasetSpec, spec.name, "dataset")
