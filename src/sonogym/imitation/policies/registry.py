"""The imitation-learning policies by name: the one table that training (``train_il``), run
folders (``imitation.run``), the env-side wrapper, evaluation, learning-curve labels and
``sonogym il-train --policy`` read.

A ``PolicySpec`` names a policy's config class, model class, the short algorithm name its runs
carry (``algo`` in a run's config.json, evaluation tables, report and curve groups) and its
display label. ``register`` adds one (a policy of your own, or a test's).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sonogym.imitation.policies.act import ACTConfig, ACTPolicy
from sonogym.imitation.policies.base import ILConfig, ILModel
from sonogym.imitation.policies.diffusion import DiffusionConfig, DiffusionPolicy

#: the config presets every policy has (``ILConfig.paper`` / ``ILConfig.cpu``)
PRESETS = ("paper", "cpu")


@dataclass(frozen=True)
class PolicySpec:
    name: str  # ``--policy`` value and a run config's "policy"
    config_cls: type[ILConfig]
    model_cls: type[ILModel]
    algo: str  # short algorithm name in run configs, tables and curves ("act", "dp")
    label: str  # display label in plots and reports ("ACT", "DP")


_POLICIES: dict[str, PolicySpec] = {}


def register(spec: PolicySpec) -> PolicySpec:
    """Add ``spec``; a name or algorithm name another policy has is refused."""
    for other in _POLICIES.values():
        if spec.name == other.name or spec.algo == other.algo:
            raise ValueError(
                f"policy {spec.name!r} (algo {spec.algo!r}) clashes with the registered "
                f"{other.name!r} (algo {other.algo!r}); choose another name"
            )
    if not (issubclass(spec.config_cls, ILConfig) and issubclass(spec.model_cls, ILModel)):
        raise TypeError(
            f"policy {spec.name!r}: its config must be an ILConfig, its model an ILModel"
        )
    _POLICIES[spec.name] = spec
    return spec


def unregister(name: str) -> None:
    """Remove the policy ``name`` (``KeyError`` if it is not registered)."""
    del _POLICIES[name]


def policy_names() -> tuple[str, ...]:
    """The registered policies' names, in registration order."""
    return tuple(_POLICIES)


def get_policy(name: str) -> PolicySpec:
    """The policy ``name``, or a ``ValueError`` listing the known ones."""
    spec = _POLICIES.get(name)
    if spec is None:
        raise ValueError(f"unknown policy {name!r}; choose one of {policy_names()}")
    return spec


def policy_for_algo(algo: str) -> PolicySpec | None:
    """The policy whose runs carry algorithm name ``algo``, or None (an RL algorithm)."""
    return next((s for s in _POLICIES.values() if s.algo == algo), None)


def make_config(name: str, preset: str = "cpu", **overrides: Any) -> ILConfig:
    """The ``paper`` or ``cpu`` preset config of policy ``name``, with ``overrides``."""
    spec = get_policy(name)
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose 'paper' or 'cpu'")
    return getattr(spec.config_cls, preset)(**overrides)


register(PolicySpec("act", ACTConfig, ACTPolicy, algo="act", label="ACT"))
register(PolicySpec("diffusion", DiffusionConfig, DiffusionPolicy, algo="dp", label="DP"))
