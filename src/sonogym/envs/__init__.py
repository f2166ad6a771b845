"""Batched Gymnasium environments of the three tasks, registered on ``import sonogym``.

``gymnasium.make_vec("SonoGym/Navigation-v0", num_envs=128, **options)`` gives the native
batched env (torch tensors, SAME_STEP autoreset); ``gymnasium.make(...)`` one env with NumPy I/O.
``sonogym.envs.registry`` holds each task's ``TaskSpec`` (metrics, expert, where its RL defaults
are).
"""

from __future__ import annotations

from sonogym.envs.registry import TASKS, get_task, make_vec, register_envs

__all__ = ["TASKS", "get_task", "make_vec", "register_envs"]

register_envs()
