"""A task's reinforcement-learning defaults: the records a task's agents module is made of
(``TrainingDefaults``, ``LearningParams``, ``CpuRecipe``, the conv trunks) and
``training_defaults(task)``, which loads that module.

Each task's agents module (``sonogym.tasks.<task>.agents``) holds its ``TrainingDefaults``: one
config per RL algorithm it trains with (the paper's tables; the algorithms and their config
classes are in ``sonogym.agents.algorithms``), and the settings every algorithm shares on that
task: how long, how many envs, the network's conv trunks, observation and reward scales,
initial exploration, and the ``cpu`` preset's recipe. The task's ``TaskSpec.agents`` names the
module by entry point (``"module:ATTRIBUTE"``), so the env package imports nothing from it.
These are plain dataclasses: no RL library is imported here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
from typing import Any

from sonogym.envs.base import check_number_fields

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
class CpuRecipe:
    """What the ``cpu`` preset trains a task with where the paper's settings do not train on
    a CPU budget (documented deviations; the env's defaults stay the paper's, and so does the
    ``paper`` preset). ``sonogym train --task T`` on a CPU trains with these."""

    algorithms: dict[str, Any] = field(default_factory=dict)  # algorithm -> its config, if other
    env_kwargs: dict[str, Any] = field(default_factory=dict)  # env options
    net: str | None = None  # network size (None: the preset's, "small")
    timesteps: int | None = None  # env steps per env (None: the task's ``timesteps``)


@dataclass(frozen=True)
class TrainingDefaults:
    """A task's RL defaults: one config per algorithm it trains with, and what every algorithm
    shares on it.

    ``algorithms`` maps an algorithm's name (``sonogym.agents.algorithms``) to its config for
    this task: the algorithms a task lists are the ones it supports. ``trunks`` maps a conv
    size ("paper", "small") to the conv layers of the task's image trunk
    (``agents.networks.NET_SIZES`` names the one each ``net`` uses: ``lean`` the small);
    ``vector_splits`` names vector observation entries the encoder splits into named parts with
    one MLP each (surgery's pose: ("pos", 3), ("quat", 4)); ``learning`` shapes observations,
    rewards and exploration; ``cpu`` is the ``cpu`` preset's recipe."""

    algorithms: dict[str, Any]  # algorithm name -> its config (the paper's table)
    timesteps: int  # env steps per env (reference trainer timesteps)
    trunks: dict[str, ConvSpec]
    num_envs: int = 128  # paper
    image_height: int | None = None  # px of the image observation (presets pool it), None: none
    learning: LearningParams = field(default_factory=LearningParams)
    cpu: CpuRecipe = field(default_factory=CpuRecipe)
    vector_splits: dict[str, tuple[tuple[str, int], ...]] = field(default_factory=dict)
    # per obs_mode, scales of the entries only that mode has (``learning.obs_scales`` applies
    # to every mode, and names only entries every mode has)
    obs_scales_by_mode: dict[str, dict[str, float]] = field(default_factory=dict)


@cache
def training_defaults(task: str) -> TrainingDefaults:
    """The ``TrainingDefaults`` of ``task`` (or of its Gymnasium id), from the module its
    ``TaskSpec.agents`` names; an unknown task names the known ones."""
    from sonogym.envs.registry import get_task
    from sonogym.envs.spec import load_entry_point

    spec = get_task(task)
    return load_entry_point(spec.agents, TrainingDefaults, spec.name, "agents")
