"""What an RL algorithm is to sonogym (``AlgorithmSpec``) and the records its hooks receive.

An algorithm is its config dataclass (its hyperparameters; each task's agents module holds its
defaults for that task), a builder that makes the skrl agent, the models it trains beside the
shared policy / value network, and how a trained run of it acts at test time (``Acting``).
Nothing here imports an RL library: builders import skrl when they run.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sonogym.envs.base import check_number_fields

#: Fields every algorithm config has: the trainer writes checkpoints at update boundaries,
#: sizes the rollout memory and checks a privileged critic's mini-batches with them.
REQUIRED_FIELDS = ("rollouts", "mini_batches")


@dataclass(frozen=True)
class AgentSetup:
    """What an algorithm's ``build`` makes its agent from."""

    task: str
    config: Any  # the algorithm's config (its ``config_cls``), resolved for this run
    learning: Any  # the task's ``LearningParams`` (reward scale, ...)
    models: dict[str, Any]  # "policy" and "value" (one module) and the algorithm's own
    observation_space: Any  # gymnasium spaces, flat (``SkrlEnvAdapter``)
    action_space: Any
    state_space: Any  # a privileged critic's states (None: the critic reads observations)
    num_envs: int
    out: Path  # the run folder: skrl's experiment directory (TensorBoard)
    device: str
    write_interval: int  # env steps between TensorBoard writes (0: none)


@dataclass(frozen=True)
class ModelSetup:
    """What an algorithm's ``models`` hook builds its extra networks from (the shared
    policy / value network is built for every algorithm)."""

    task: str
    layout: Any  # the flat observation's layout (``adapter.ObsLayout``)
    action_space: Any
    device: str
    net: str  # network size (``networks.NET_SIZES``)


@dataclass(frozen=True)
class ActingSetup:
    """What an algorithm's ``Acting.policy`` hook makes an acting policy from."""

    policy: Any  # ``checkpoint.RLPolicy``: the run's Gaussian mean through its adapter
    run: Path  # the run folder
    config: dict[str, Any]  # its config.json (``checkpoint.run_config``)
    checkpoint: Path  # the checkpoint being evaluated
    device: str
    controller: str  # "policy" or one of ``Acting.controllers``
    settings: dict[str, Any]  # the test-time settings (``Acting.settings``; {}: none)


@dataclass(frozen=True)
class ActingSettings:
    """Test-time settings of an algorithm's acting that evaluation may override without
    retraining (a ``ppo-sf`` run's safety filter)."""

    name: str  # their name in ``evaluate_run`` and eval.json ("safety_filter")
    #: ``resolve(run config, given)`` -> the settings evaluated with: the run's, ``given``
    #: (None values: the run's) on top; ValueError for a setting it does not take
    resolve: Callable[[dict, dict], dict]


@dataclass(frozen=True)
class Acting:
    """How a trained run of an algorithm acts at test time (``sonogym eval``, shipped
    policies). The defaults: the Gaussian's mean action, nothing else."""

    #: checkpoint entries acting reads beyond "policy" and "obs_standardizer" (a shipped
    #: policy's weights keep them)
    modules: tuple[str, ...] = ()
    #: ``policy(ActingSetup)`` -> the acting ``Policy`` of controller ``setup.controller``;
    #: None: ``setup.policy`` as it is
    policy: Callable[[ActingSetup], Any] | None = None
    #: controllers evaluation runs beyond "policy", "expert" and "random" (by default right
    #: after "policy"); ``policy`` builds them
    controllers: tuple[str, ...] = ()
    #: test-time settings evaluation may override; None: it takes none
    settings: ActingSettings | None = None


@dataclass(frozen=True)
class AlgorithmSpec:
    """One RL algorithm: what ``register`` adds and ``--algo`` names.

    ``build(AgentSetup)`` returns the skrl agent (an ``skrl.agents.torch.Agent``: the training
    loop calls ``init``, ``act``, ``record_transition``, ``pre_interaction`` and
    ``post_interaction``, and checkpoints its ``checkpoint_modules``). ``models(ModelSetup)``
    returns the networks it trains beside the shared policy / value (e.g. a cost critic), by
    skrl role. ``defaults`` gives its config per task for tasks whose agents module has none
    (an algorithm of your own; a task's module wins where it has one)."""

    name: str  # ``--algo`` value and a run config's "algo"
    label: str  # plots and reports ("PPO + SF")
    config_cls: type  # a frozen dataclass with at least ``REQUIRED_FIELDS``
    build: Callable[[AgentSetup], Any]
    models: Callable[[ModelSetup], dict[str, Any]] | None = None
    acting: Acting = field(default_factory=Acting)
    defaults: Mapping[str, Any] = field(default_factory=dict)  # task name -> config

    def __post_init__(self) -> None:
        if not (isinstance(self.config_cls, type) and dataclasses.is_dataclass(self.config_cls)):
            raise TypeError(f"algorithm {self.name!r}: config_cls must be a dataclass")
        names = {f.name for f in dataclasses.fields(self.config_cls)}
        missing = [f for f in REQUIRED_FIELDS if f not in names]
        if missing:
            raise TypeError(
                f"algorithm {self.name!r}: {self.config_cls.__name__} lacks {missing}, which "
                "the trainer reads (rollouts: env steps per env between updates; mini_batches: "
                "how many batches an update splits them into)"
            )
        for task, config in self.defaults.items():
            if not isinstance(config, self.config_cls):
                raise TypeError(
                    f"algorithm {self.name!r}: its {task} default is a "
                    f"{type(config).__name__}, not a {self.config_cls.__name__}"
                )


def check_on_policy_params(p: Any, counts: tuple[str, ...]) -> None:
    """Refuse settings no run can train with, naming the field: counts below 1, a learning rate
    that is not positive, a discount or GAE lambda outside [0, 1], a negative clip, and any
    NaN, inf or non-integer count (``check_number_fields``)."""
    check_number_fields(p)
    name = type(p).__name__
    for f in counts:
        if getattr(p, f) < 1:
            raise ValueError(f"{name}.{f} must be >= 1, got {getattr(p, f)}")
    if not p.learning_rate > 0:
        raise ValueError(f"{name}.learning_rate must be > 0, got {p.learning_rate}")
    for f in ("discount_factor", "gae_lambda"):
        if not 0 <= getattr(p, f) <= 1:
            raise ValueError(f"{name}.{f} must be in [0, 1], got {getattr(p, f)}")
    for f in ("kl_threshold", "grad_norm_clip", "value_clip", "ratio_clip", "value_loss_scale"):
        if getattr(p, f, 0) < 0:
            raise ValueError(f"{name}.{f} must be >= 0, got {getattr(p, f)}")
