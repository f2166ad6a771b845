"""The interface every imitation-learning policy implements: a config and a model.

``ILConfig`` is the base of a policy's frozen-dataclass config: its model sizes (``paper``,
``cpu``), (de)serialisation for a run's config.json, and what the policy needs of the data and
of the env loop (dataset offsets, frames left out at episode ends, observation history length,
chunk length, temporal ensembling). ``ILModel`` is the base of its ``nn.Module``: the loss of a
dataset batch, chunk prediction, optimiser and learning-rate schedule; it holds the
``Normalizer`` so that the dataset statistics travel in the checkpoint, and normalises inputs
and unnormalises predicted actions once for every policy.

Trainer (``train_il``), env-side wrapper (``ILPolicy``), run folders and evaluation use these
and the registry (``policies.registry``) only, never a concrete policy class.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar

import torch
from torch import nn

from sonogym.imitation.processor import ACTION_KEY, Normalizer, PolicyFeatures, norm_modes

#: dataset statistics a model normalises with: {key: {"mean", "std", "min", "max": tensor}}
Stats = dict[str, dict[str, torch.Tensor]]


class ILConfig(abc.ABC):
    """Base of a policy config, which is a frozen dataclass with (at least) these fields:

    n_action_steps: actions executed per predicted chunk when not ensembling, >= 1.
    grad_clip_norm: gradient-norm clip of a training step.
    visual_norm, state_norm, action_norm: normalisation modes ("mean_std", "min_max",
        "identity") of images, state and action.

    Optional fields, with these defaults here: ``image_size`` ((H, W) px images are resampled
    to; None: images must come at the dataset's size) and ``temporal_ensemble_coeff`` (None:
    chunks are executed ``n_action_steps`` at a time; a number: a chunk every step, averaged by
    the temporal ensemble, LeRobot's ACT semantics).
    """

    image_size: tuple[int, int] | None = None
    temporal_ensemble_coeff: float | None = None
    #: field values of the ``cpu`` size (a model that trains on 2 CPU cores)
    CPU_SIZE: ClassVar[dict[str, Any]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "CPU_PRESET" in cls.__dict__:  # refused, not ignored: its cpu size would be lost
            raise TypeError(f"{cls.__name__}.CPU_PRESET is not read: name it CPU_SIZE")

    @classmethod
    def paper(cls, **overrides: Any) -> ILConfig:
        """The paper's (LeRobot's) settings: the dataclass defaults."""
        return cls(**overrides)

    @classmethod
    def cpu(cls, **overrides: Any) -> ILConfig:
        """The small ``CPU_SIZE`` model."""
        return cls(**{**cls.CPU_SIZE, **overrides})

    def to_dict(self) -> dict[str, Any]:
        """The config as a run's config.json holds it (``from_dict`` reads it back)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ILConfig:
        """The config of ``to_dict``'s (JSON-read) dict: lists become tuples, keys a later
        version dropped are ignored."""
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names}
        )

    @abc.abstractmethod
    def delta_indices(self, features: PolicyFeatures) -> dict[str, list[int]]:
        """Frame offsets of each training sample's features (``LeRobotFrames``): observation
        history and action chunk."""

    @property
    def drop_n_last_frames(self) -> int:
        """Frames at each episode's end not used as training samples."""
        return 0

    @property
    def observation_steps(self) -> int | None:
        """Observation history the model reads: None, the current observation (B, ...); n,
        the last n observations (B, n, ...), oldest first."""
        return None

    @property
    @abc.abstractmethod
    def chunk_length(self) -> int:
        """Actions per ``predict_chunk`` call (the temporal ensemble's window)."""


class ILModel(nn.Module, abc.ABC):
    """Base of a policy model over a dataset's ``features``, normalised with ``stats``.

    A subclass builds its layers after ``super().__init__(config, features, stats)`` and
    implements ``loss`` and ``predict`` on normalised values, and ``optimizer``; it may
    override ``lr_lambda`` (default: a constant rate).
    """

    def __init__(self, config: ILConfig, features: PolicyFeatures, stats: Stats) -> None:
        super().__init__()
        self.config = config
        self.features = features
        if not features.image_keys and not features.state_dim:
            raise ValueError(
                f"{type(self).__name__} needs image features or observation.state as input"
            )
        self.normalizer = Normalizer(
            stats,
            norm_modes(features, config.visual_norm, config.state_norm, config.action_norm),
        )

    # --- what a policy implements ---------------------------------------------------------

    @abc.abstractmethod
    def loss(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator | None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """(loss, {term: value}) of a normalised training batch (``delta_indices`` stacking,
        ``<key>_is_pad`` masks unchanged); ``generator`` drives the model's own noise."""

    @abc.abstractmethod
    def predict(
        self, obs: dict[str, torch.Tensor], generator: torch.Generator | None
    ) -> torch.Tensor:
        """Normalised actions (B, chunk_length, A) for normalised observations, in eval mode
        without gradients."""

    @abc.abstractmethod
    def optimizer(self) -> torch.optim.Optimizer:
        """The training optimiser over this model's parameters."""

    def lr_lambda(self, total_steps: int) -> Callable[[int], float]:
        """Learning-rate factor per optimiser step (``LambdaLR``) for a run of
        ``total_steps``."""
        return lambda step: 1.0

    # --- shared by every policy -----------------------------------------------------------

    def compute_loss(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Training loss of a dataset batch in raw units: (loss, {term: value})."""
        return self.loss(self.normalizer(batch), generator)

    @torch.no_grad()
    def predict_chunk(
        self, obs: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Actions (B, chunk_length, A) in dataset units for raw observations (images
        (B[, n], C, H, W) in [0, 1], state (B[, n], D); n = ``observation_steps``), predicted
        in eval mode (the training mode is restored after)."""
        was = self.training
        self.eval()
        chunk = self.predict(self.normalizer(obs), generator)
        self.train(was)
        return self.normalizer.unnormalize(ACTION_KEY, chunk)
