"""How ``sonogym demo`` shows a task: the ``Demo`` record a task's demo module holds
(``sonogym.tasks.<task>.demo``) and ``task_demo(task)``, which loads that module.

The task's ``TaskSpec.demo`` names the module by entry point (``"module:ATTRIBUTE"``), so the
env package imports nothing from it; the drawing itself is NumPy over the env's public state
(``sonogym.envs.frames``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
import torch


@dataclass(frozen=True)
class Demo:
    """How ``sonogym demo`` shows a task: ``image(obs)`` env 0's 2-D image in [0, 1] for the
    frame sheet; ``frame(env, image, path)`` one RGB video frame (uint8 H x W x 3, sides
    multiples of 16), ``path`` the tracked points so far (``Track`` columns, metres / rad)."""

    image: Callable[[Any], torch.Tensor]
    frame: Callable[[Any, torch.Tensor, np.ndarray], np.ndarray]
    point: Callable[[Any, dict[str, Any]], np.ndarray]  # env 0's point drawn on the path


@cache
def task_demo(task: str) -> Demo:
    """The ``Demo`` of ``task`` (or of its Gymnasium id), from the module its ``TaskSpec.demo``
    names; an unknown task names the known ones."""
    from sonogym.envs.registry import get_task
    from sonogym.envs.spec import load_entry_point

    spec = get_task(task)
    return load_entry_point(spec.demo, Demo, spec.name, "demo")
