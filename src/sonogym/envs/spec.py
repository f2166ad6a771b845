"""What a task is, in one record: ``TaskSpec`` and the plain-data pieces it is made of.

Each task module (``navigation``, ``reconstruction``, ``surgery``) ends with its ``SPEC``;
``sonogym.envs.registry`` lists them. Everything outside ``envs/`` that needs to know about a
task (training, evaluation, the demo, dataset recording, reports) reads it from the spec, so a
new task is one new module plus one registry entry.

The spec is plain data and small functions over the env's public API (no RL, plotting or CLI
library): metrics with units and better-direction, the trajectory evaluation logs, the demo's
frames, the observation -> LeRobot feature mapping for imitation learning, and the paper's
per-algorithm hyperparameters and initial exploration (Isaac Lab task folders carry their
agents' configs the same way).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch

from sonogym.envs.base import check_number_fields

ExpertFn = Callable[[Any, dict[str, Any]], torch.Tensor]

#: Conv layers of an image trunk: (out_channels, kernel, stride) per layer.
ConvSpec = tuple[tuple[int, int, int], ...]

#: The paper's / reference's trunks (ReLU convs without padding): four layers for the 2-D
#: navigation image, three for the reconstruction cube and the surgery volume.
CONV4: ConvSpec = ((32, 8, 2), (64, 4, 2), (64, 4, 2), (64, 3, 1))
CONV3: ConvSpec = ((32, 8, 2), (64, 4, 2), (64, 3, 1))
#: CPU-sized trunks with the same layer counts (narrower, smaller kernels; fit downsampled
#: images the k8 kernels do not).
SMALL_CONV4: ConvSpec = ((16, 5, 2), (32, 3, 2), (32, 3, 2), (32, 3, 1))
SMALL_CONV3: ConvSpec = ((16, 5, 2), (32, 3, 2), (32, 3, 1))


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


@dataclass(frozen=True)
class Demo:
    """How ``sonogym demo`` shows a task: ``image(obs)`` env 0's 2-D image in [0, 1] for the
    frame sheet; ``frame(env, image, path)`` one RGB video frame (uint8 H x W x 3, sides
    multiples of 16), ``path`` the tracked points so far (``Track`` columns, metres / rad)."""

    image: Callable[[Any], torch.Tensor]
    frame: Callable[[Any, torch.Tensor, np.ndarray], np.ndarray]
    point: Callable[[Any, dict[str, Any]], np.ndarray]  # env 0's point drawn on the path


@dataclass(frozen=True)
class PPOParams:
    """skrl PPO settings (paper Tab. ppo_hype; what it leaves open from the reference)."""

    rollouts: int  # env steps per env between updates
    learning_epochs: int
    mini_batches: int
    learning_rate: float  # initial, per optimiser step, adapted by KLAdaptiveLR
    value_clip: float  # clip of the predicted value's change (value units, standardised)
    discount_factor: float = 0.99
    gae_lambda: float = 0.95
    kl_threshold: float = 0.008  # KLAdaptiveLR target KL (not early stopping)
    grad_norm_clip: float = 1.0
    ratio_clip: float = 0.2
    value_loss_scale: float = 1.0
    entropy_loss_scale: float = 0.0  # reference
    time_limit_bootstrap: bool = True  # see sonogym.agents.configs

    def __post_init__(self) -> None:
        check_algo_params(self, ("rollouts", "learning_epochs", "mini_batches"))


@dataclass(frozen=True)
class A2CParams:
    """skrl A2C settings (paper Tab. a2c_hype; A2C has no epochs: the table's
    ``learning_epochs`` is not an A2C setting and is not used)."""

    rollouts: int  # env steps per env between updates
    mini_batches: int
    learning_rate: float = 1e-4  # initial, adapted by KLAdaptiveLR (reference)
    discount_factor: float = 0.99
    gae_lambda: float = 0.95
    kl_threshold: float = 0.008
    grad_norm_clip: float = 1.0
    entropy_loss_scale: float = 0.0
    time_limit_bootstrap: bool = True

    def __post_init__(self) -> None:
        check_algo_params(self, ("rollouts", "mini_batches"))


def check_algo_params(p: PPOParams | A2CParams, counts: tuple[str, ...]) -> None:
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


@dataclass(frozen=True)
class SafetyParams:
    """Settings of the safe-RL algorithms (``ppo-sf``, ``ppo-lag``) on a task with a cost."""

    cost_learning_rate: float = 1e-4  # Adam lr of the cost critic / cost value (reference)
    cost_threshold: float = 0.5  # ppo-sf: filter where Q_c(o, a) > this (reference; c in [0, 1])
    filter_mode: str = "search"  # ppo-sf at test time: "search" (ours) or "zero" (the paper's)
    cost_limit: float = 5.0  # ppo-lag: limit on the mean discounted cost return (cost units)
    pid_gains: tuple[float, float, float] = (0.05, 0.0005, 0.1)  # ppo-lag: Kp, Ki, Kd

    def __post_init__(self) -> None:
        check_number_fields(self)


@dataclass(frozen=True)
class LearningParams:
    """How a task's observations, rewards and policy are shaped for learning, whatever the
    algorithm: observation and reward scales, the Gaussian policy's initial exploration and
    its optional narrowing, and the training env's episode staggering.

    ``init_log_std`` is the Gaussian policy's initial log standard deviation in action units
    (exploration); ``final_log_std`` (None: off) is a ceiling on it that falls linearly in log
    space from ``init_log_std`` to this value over the first ``anneal_steps`` env steps per env,
    then stays (exploration that narrows as the policy sharpens; PPO may still shrink sigma
    faster)."""

    obs_scales: dict[str, float] = field(default_factory=dict)  # per entry, unitless
    reward_scale: float = 1.0  # unitless factor on rewards before learning
    init_log_std: float = 0.0  # log of sigma in action units
    final_log_std: float | None = None  # log sigma ceiling after anneal_steps (None: no ceiling)
    anneal_steps: int = 0  # env steps per env over which the ceiling falls
    init_mean_gain: float = 1.0  # factor on the mean head's initial weights (0.01: acts ~0)
    mean_bound_penalty: float = 0.0  # weight of the loss on the policy mean outside the box
    bounded_mean: bool = False  # policy mean squashed into the action box (tanh), see networks
    stagger_episodes: bool = False  # training: first episodes end at random steps (base env)
    standardize_vectors: bool = False  # running standardisation of vector observations
    standardize_steps: int = 0  # env steps per env the statistics learn for (0: the whole run)
    kl_follows_sigma: bool = False  # KL-adaptive lr threshold scaled by (sigma_0 / ceiling)^2
    privileged_critic: bool = False  # training: the value also reads info["state"] (networks)

    def __post_init__(self) -> None:
        check_number_fields(self)  # NaN, inf; 2.0 steps becomes 2


@dataclass(frozen=True)
class TrainingDefaults:
    """A task's RL defaults: the paper's tables and what the network needs to know.

    ``trunks`` maps a conv size ("paper", "small") to the conv layers of the task's image
    trunk (``agents.networks.NET_SIZES`` names the one each ``net`` uses: ``lean`` the
    small); ``vector_splits`` names vector observation entries the encoder splits into named
    parts with one MLP each (surgery's pose: ("pos", 3), ("quat", 4)); ``learning`` shapes
    observations, rewards and exploration (``LearningParams``); ``safety`` configures the
    safe-RL algorithms of a task with a cost."""

    algos: tuple[str, ...]
    ppo: PPOParams  # the paper's table
    a2c: A2CParams
    timesteps: int  # env steps per env (reference trainer timesteps)
    trunks: dict[str, ConvSpec]
    num_envs: int = 128  # paper
    image_height: int | None = None  # px of the image observation (presets pool it), None: none
    learning: LearningParams = field(default_factory=LearningParams)
    # The ``cpu`` preset's recipe: what trains best on a CPU budget where the paper's settings
    # do not (documented deviations; the env's defaults stay the paper's, and so does the
    # ``paper`` preset). ``sonogym train --task T`` on a CPU trains with these.
    ppo_cpu: PPOParams | None = None  # the PPO table, if different
    env_kwargs_cpu: dict[str, Any] = field(default_factory=dict)  # env options
    net_cpu: str | None = None  # network size (None: the preset's, "small")
    timesteps_cpu: int | None = None  # env steps per env (None: ``timesteps``)
    vector_splits: dict[str, tuple[tuple[str, int], ...]] = field(default_factory=dict)
    # per obs_mode, scales of the entries only that mode has (``learning.obs_scales`` applies
    # to every mode, and names only entries every mode has)
    obs_scales_by_mode: dict[str, dict[str, float]] = field(default_factory=dict)
    safety: SafetyParams | None = None  # tasks with a cost (ppo-sf, ppo-lag)


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
    (reconstruction), named by ``expert_label``; ``dataset`` is None for a task without
    expert datasets for imitation learning."""

    name: str
    env_id: str
    env_cls: type
    config_cls: type
    action_names: tuple[str, ...]  # one per action component, as datasets name them
    expert: ExpertFn
    expert_label: Literal["expert", "heuristic"]
    metrics: tuple[Metric, ...]
    track: Track
    demo: Demo
    training: TrainingDefaults
    memory: EnvMemory  # what ``sonogym.envs.footprint`` estimates a run's memory from
    dataset: DatasetSpec | None = None
    # per obs_mode, the version of what the observation means (absent: 1); bumped when it
    # changes, so a policy trained on an older one is refused instead of silently misread
    obs_versions: dict[str, int] = field(default_factory=dict)
    #: the task definition's version (reward, goal, regions, start distribution, episode
    #: length): bumped whenever one of them changes, so results record which task they measure
    #: (``sonogym.envs.identity``)
    version: int = 1

    @property
    def default_obs_mode(self) -> str | None:
        """The env config's default ``obs_mode`` (None: the config has no such field)."""
        return getattr(self.config_cls(), "obs_mode", None)

    def obs_version(self, obs_mode: str | None) -> int:
        """The version of observation ``obs_mode`` (None: the env config's default mode)."""
        if obs_mode is None:
            obs_mode = self.default_obs_mode
        return self.obs_versions.get(obs_mode, 1)

    def metric(self, key: str) -> Metric:
        for m in self.metrics:
            if m.key == key:
                return m
        raise KeyError(f"{self.name} has no metric {key!r}; metrics: {self.metric_keys}")

    @property
    def metric_keys(self) -> tuple[str, ...]:
        return tuple(m.key for m in self.metrics)
