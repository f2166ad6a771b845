"""What a task is, in one record: ``TaskSpec`` and the plain-data pieces it is made of.

Each task module (``navigation``, ``reconstruction``, ``surgery``) ends with its ``SPEC``;
``sonogym.envs.registry`` lists them. Everything outside ``envs/`` that needs to know about a
task (training, evaluation, the demo, dataset recording, reports) reads it from the spec, so a
new task is one new module plus one registry entry.

The spec holds the env's facts as plain data and small functions over the env's public API
(no RL, plotting or CLI library): metrics with units and better-direction, the trajectory
evaluation logs, the expert, the versions and the env's measured memory. What the tools make of
a task lives beside it in ``sonogym.tasks.<task>``, named by entry point (``"module:ATTRIBUTE"``,
loaded by its reader with ``load_entry_point``): its RL settings (``TaskSpec.agents``), its
expert datasets for imitation learning (``TaskSpec.dataset``) and how ``sonogym demo`` shows
it (``TaskSpec.demo``). The env package imports nothing from there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import torch

ExpertFn = Callable[[Any, dict[str, Any]], torch.Tensor]


@dataclass(frozen=True)
class Metric:
    """One episode metric: the env's ``final_info`` key, the paper's label, the unit it is
    reported in, the factor from the env's unit to that unit, and which direction is better."""

    key: str
    label: str
    unit: str
    scale: float = 1.0
    better: Literal["lower", "higher"] = "lower"
    #: Evaluation tables also count the episodes within this of the goal (in the env's unit,
    #: on the ``better`` side), e.g. navigation's 10 mm; None: no such count.
    tolerance: float | None = None


@dataclass(frozen=True)
class Track:
    """The trajectory evaluation logs per step: ``fn(env, info)`` -> (N, D) in ``units``;
    ``plane`` names the two columns the trajectory figure draws (horizontal, vertical);
    ``axis_line``: the figure also draws the vertical line through the goal (a planned
    trajectory along the vertical axis)."""

    columns: tuple[str, ...]
    units: tuple[str, ...]
    fn: Callable[[Any, dict[str, Any]], torch.Tensor]
    plane: tuple[str, str]
    axis_line: bool = False


@dataclass(frozen=True)
class EnvMemory:
    """A task env's resident memory, measured on the CPU as the RSS growth of a fresh process
    that builds the env with its default options and steps it with the expert
    (``sonogym.envs.footprint`` documents the runs): bytes per env, bytes per patient at 1 mm
    voxels, and the transient of loading one patient at 1 mm. The patient terms scale with the
    voxel count, (1 mm / spacing)^3."""

    per_env: float  # bytes
    per_patient: float  # bytes at 1 mm voxels
    load_peak: float  # bytes at 1 mm voxels


@dataclass(frozen=True)
class TaskSpec:
    """Everything the rest of the package knows about a task (see the module docstring).

    ``expert(env, info)`` is the privileged expert (navigation, surgery) or heuristic
    (reconstruction), named by ``expert_label``; ``experts`` names further privileged
    experts, each a factory ``make(env)`` of a ``Policy`` (per-env state allowed), that a DAgger
    warm start may imitate (``sonogym.agents.dagger``). ``agents``, ``demo`` and ``dataset``
    name the task's tool settings by entry point (module docstring); ``dataset`` is None for a
    task without expert datasets for imitation learning."""

    name: str
    env_id: str
    env_cls: type
    config_cls: type
    action_names: tuple[str, ...]  # one per action component, as datasets name them
    expert: ExpertFn
    expert_label: Literal["expert", "heuristic"]
    metrics: tuple[Metric, ...]
    track: Track
    #: how ``sonogym demo`` shows the task, "module:ATTRIBUTE" of a ``Demo``
    #: (``sonogym.tasks.demo``), loaded by ``sonogym.evaluation.demo``, never here
    demo: str
    #: the task's RL defaults, "module:ATTRIBUTE" of a ``TrainingDefaults``
    #: (``sonogym.agents.task_defaults``), loaded by the agents package, never here
    agents: str
    memory: EnvMemory  # what ``sonogym.envs.footprint`` estimates a run's memory from
    #: the task's expert datasets, "module:ATTRIBUTE" of a ``DatasetSpec``
    #: (``sonogym.imitation.task_datasets``), loaded by the imitation package, never here;
    #: None: the task has none
    dataset: str | None = None
    # per obs_mode, the version of what the observation means (absent: 1); bumped when it
    # changes, so a policy trained on an older one is refused instead of silently misread
    obs_versions: dict[str, int] = field(default_factory=dict)
    #: the task definition's version (reward, goal, regions, start distribution, episode
    #: length): bumped whenever one of them changes, so results record which task they measure
    #: (``sonogym.envs.identity``)
    version: int = 1
    #: further privileged experts by name: "module:ATTRIBUTE" of ``make(env)`` -> a ``Policy``
    experts: dict[str, str] = field(default_factory=dict)

    @property
    def default_obs_mode(self) -> str | None:
        """The env config's default ``obs_mode`` (None: the config has no such field)."""
        return getattr(self.config_cls(), "obs_mode", None)

    def obs_version(self, obs_mode: str | None) -> int:
        """The version of observation ``obs_mode`` (None: the env config's default mode)."""
        if obs_mode is None:
            obs_mode = self.default_obs_mode
        return self.obs_versions.get(obs_mode, 1)

    def expert_factory(self, name: str) -> Callable[[Any], Any]:
        """The factory ``make(env)`` of the further expert ``name`` (``experts``); a name the
        task lacks is refused, naming the ones it has."""
        import importlib

        if name not in self.experts:
            raise ValueError(
                f"{self.name} has no expert {name!r}; its further experts: {list(self.experts)}"
            )
        module, _, attr = self.experts[name].partition(":")
        return getattr(importlib.import_module(module), attr)

    def metric(self, key: str) -> Metric:
        for m in self.metrics:
            if m.key == key:
                return m
        raise KeyError(f"{self.name} has no metric {key!r}; metrics: {self.metric_keys}")

    @property
    def metric_keys(self) -> tuple[str, ...]:
        return tuple(m.key for m in self.metrics)


def load_entry_point(ref: str, cls: type, task: str, field_name: str) -> Any:
    """The object ``ref`` ("package.module:ATTRIBUTE", task ``task``'s ``TaskSpec.<field_name>``)
    names, which must be a ``cls``: a malformed reference is a ``ValueError``, an object of
    another type a ``TypeError``, each naming the task and the field."""
    import importlib

    module, _, attr = ref.partition(":")
    if not module or not attr:
        raise ValueError(
            f"task {task!r} names no {field_name} config (TaskSpec.{field_name} {ref!r}); "
            "give it as 'package.module:ATTRIBUTE'"
        )
    obj = getattr(importlib.import_module(module), attr, None)
    if not isinstance(obj, cls):
        raise TypeError(f"{ref} (task {task!r}) is not a {cls.__name__}")
    return obj
