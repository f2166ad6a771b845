"""The task registry: every SonoGym task's ``TaskSpec``, by name and by Gymnasium id.

Adding a task: write its module (env, config, expert, ``SPEC``) and add it to ``_MODULES``;
its RL defaults go beside it in ``sonogym.tasks.<task>.agents`` (``TaskSpec.agents``).
Nothing else in the package keeps a per-task table.
"""

from __future__ import annotations

import gymnasium as gym

from sonogym.envs import navigation, reconstruction, surgery
from sonogym.envs.base import make_config
from sonogym.envs.spec import TaskSpec

_MODULES = (navigation, reconstruction, surgery)

#: Task name -> spec, in the paper's order.
TASKS: dict[str, TaskSpec] = {m.SPEC.name: m.SPEC for m in _MODULES}


def task_names() -> tuple[str, ...]:
    return tuple(TASKS)


def get_task(name: str) -> TaskSpec:
    """The spec of task ``name`` (or of its Gymnasium id), naming the known tasks if unknown."""
    if name in TASKS:
        return TASKS[name]
    for spec in TASKS.values():
        if spec.env_id == name:
            return spec
    raise ValueError(f"unknown task {name!r}; known tasks: {sorted(TASKS)}")


def check_task_name(task: object, where: object) -> str:
    """``task`` as a file read from disk (``where``, e.g. a run's config.json) gives it: one of
    the registered task names exactly, since it names files and folders; anything else (an
    edited or foreign file) is refused, naming the file and the known tasks."""
    if not isinstance(task, str) or task not in TASKS:
        raise ValueError(
            f"{where}: task {task!r} is not a sonogym task (known: {sorted(TASKS)}); the file "
            "was edited or not written by sonogym: restore it"
        )
    return task


def env_config(task: str, options: dict):
    """The task's env config with ``options`` (its fields), built without building the env:
    ``ValueError`` names an unknown option (with the valid ones) or a value the config
    refuses, so a run can be checked before it starts."""
    spec = get_task(task)
    try:
        return make_config(spec.config_cls, dict(options))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{task} env options: {e}") from None


def make_vec(task: str, num_envs: int, **options):
    """The task's batched env through ``gymnasium.make_vec`` (options: its config fields)."""
    return gym.make_vec(get_task(task).env_id, num_envs=num_envs, **options)


def register_envs() -> None:
    """Register every task with Gymnasium (idempotent): ``gymnasium.make_vec`` gives the batched
    env, ``gymnasium.make`` one env with NumPy I/O."""
    for spec in TASKS.values():
        if spec.env_id in gym.registry:
            continue
        module = spec.env_cls.__module__
        gym.register(
            id=spec.env_id,
            entry_point=f"{module}:make_single",
            vector_entry_point=f"{module}:{spec.env_cls.__name__}",
            disable_env_checker=False,
        )
