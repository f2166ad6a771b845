"""The RL algorithms by name: the one table that ``sonogym train --algo``, sweeps, run
configs, evaluation and learning-curve labels read.

An algorithm is one folder here (``ppo``, ``a2c``, ``ppo_sf``, ``ppo_lag``): its config
dataclass (``config.py``), its ``AlgorithmSpec`` with the builder and hooks
(``algorithm.py``), and its skrl agent where it has its own (``agent.py``). Each task's agents
module (``sonogym.tasks.<task>.agents``) holds the algorithm's config for that task; the
algorithms a task lists there are the ones it supports. ``register`` adds an algorithm (one of
your own, or a test's); its ``defaults`` give its config for the tasks it runs on.
"""

from __future__ import annotations

from typing import Any

from sonogym.agents.algorithms.a2c import A2C_ALGORITHM
from sonogym.agents.algorithms.base import (
    Acting,
    ActingSettings,
    ActingSetup,
    AgentSetup,
    AlgorithmSpec,
    ModelSetup,
)
from sonogym.agents.algorithms.ppo import PPO_ALGORITHM
from sonogym.agents.algorithms.ppo_lag import PPO_LAG_ALGORITHM
from sonogym.agents.algorithms.ppo_sf import PPO_SF_ALGORITHM

__all__ = [
    "Acting",
    "ActingSettings",
    "ActingSetup",
    "AgentSetup",
    "AlgorithmSpec",
    "ModelSetup",
    "algo_config",
    "algorithm_names",
    "check_algo",
    "get_algorithm",
    "register",
    "task_algorithms",
    "unregister",
]

_ALGORITHMS: dict[str, AlgorithmSpec] = {}


def register(spec: AlgorithmSpec) -> AlgorithmSpec:
    """Add ``spec``; a name another algorithm has is refused."""
    if not isinstance(spec, AlgorithmSpec):
        raise TypeError(f"register takes an AlgorithmSpec, got {type(spec).__name__}")
    if spec.name in _ALGORITHMS:
        raise ValueError(f"algorithm {spec.name!r} is registered already; choose another name")
    _ALGORITHMS[spec.name] = spec
    return spec


def unregister(name: str) -> None:
    """Remove the algorithm ``name`` (``KeyError`` if it is not registered)."""
    del _ALGORITHMS[name]


def algorithm_names() -> tuple[str, ...]:
    """The registered algorithms' names, in registration order."""
    return tuple(_ALGORITHMS)


def get_algorithm(name: str) -> AlgorithmSpec:
    """The algorithm ``name``, or a ``ValueError`` listing the known ones."""
    spec = _ALGORITHMS.get(name) if isinstance(name, str) else None
    if spec is None:
        raise ValueError(f"unknown algorithm {name!r}; known algorithms: {list(_ALGORITHMS)}")
    return spec


def _configs(task: str, preset: str) -> dict[str, Any]:
    """{algorithm: config} the task's agents module gives (the ``cpu`` preset's where its
    recipe has one)."""
    from sonogym.agents.task_defaults import training_defaults

    defaults = training_defaults(task)
    return {**defaults.algorithms, **(defaults.cpu.algorithms if preset == "cpu" else {})}


def task_algorithms(task: str) -> tuple[str, ...]:
    """The registered algorithms with a config for ``task`` (its agents module's, or the
    algorithm's own ``defaults``), in registration order; an unknown task names the known
    ones."""
    from sonogym.envs.registry import get_task

    name, own = get_task(task).name, _configs(task, "paper")
    return tuple(a for a, s in _ALGORITHMS.items() if a in own or name in s.defaults)


def check_algo(task: str, algo: str) -> AlgorithmSpec:
    """The algorithm's spec; ``ValueError`` for an unknown task, an unknown algorithm (naming
    the known ones) or one the task has no config for (naming the ones it has)."""
    from sonogym.envs.registry import get_task

    get_task(task)
    spec = get_algorithm(algo)
    supported = task_algorithms(task)
    if algo not in supported:
        raise ValueError(
            f"algorithm {algo!r} is not supported on {task}; supported: {list(supported)}"
        )
    return spec


def algo_config(task: str, algo: str, preset: str = "paper") -> Any:
    """The config of ``algo`` on ``task``: the task's agents module's (the ``cpu`` preset's
    where its recipe has one), else the algorithm's own default for the task."""
    from sonogym.envs.registry import get_task

    spec = check_algo(task, algo)
    config = _configs(task, preset).get(algo)
    if config is None:
        config = spec.defaults[get_task(task).name]
    if not isinstance(config, spec.config_cls):
        raise TypeError(
            f"{task}'s {algo} config is a {type(config).__name__}, not a {spec.config_cls.__name__}"
        )
    return config


for _spec in (PPO_ALGORITHM, A2C_ALGORITHM, PPO_SF_ALGORITHM, PPO_LAG_ALGORITHM):
    register(_spec)
