"""The ultrasound simulators by name: the one table that the envs, the benchmark identity, the
evaluation protocols, rendering and the CLI read, so that none of them branches on a name.

A ``SimulatorSpec`` says what a simulator needs and how it is built for a scene:

* ``build(patients, device, options)``: the ``UltrasoundSimulator`` imaging those patients,
  from the env options of ``SimulatorOptions`` it reads;
* ``identity(options)``: what records it in results (``sonogym.envs.identity``);
* ``draws_net``: it images each env with one of several learned nets, drawn per env at every
  episode reset after the task's own draws (so a seed gives the same episode as a model-based
  simulator), the draw passed to ``simulate`` in ``Slices.net_index``;
* ``needs_volumes``: its build reads the patients' whole volumes (a model-based simulator
  needs only the slices);
* ``group``: the paper's simulator group in tables and plots, "MB" (model-based) or "LB"
  (learning-based);
* ``dynamic_range``: dB its display image spans (the baseline of imaging randomisation);
* ``randomized``: how the episode's display settings apply to its images (default: on the
  display image, ``randomized_from_display``);
* ``view``: its image for viewing (``sonogym image``; default ``simulate``).

The built-in simulators are ``physical`` and ``reference`` (model-based) and ``learned``
(pix2pix nets). ``register`` adds one::

    register(SimulatorSpec(
        "mine", build=lambda patients, device, options: MySimulator(patients, device),
        identity=lambda options: {"model": "mine", "version": 1},
    ))

after which ``simulator="mine"`` works in every env, protocol and command. ``sonogym`` is the
former name of ``reference``, accepted with a ``DeprecationWarning`` until 0.3.0 removes it;
``canonical_name`` resolves it before anything records it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from sonogym.ultrasound.aliases import ALIASES, alias_note, canonical_name, is_alias
from sonogym.ultrasound.protocol import UltrasoundSimulator
from sonogym.ultrasound.randomization import (
    NOMINAL_DYNAMIC_RANGE,
    randomized_display,
    randomized_from_display,
)
from sonogym.ultrasound.simulator import MODEL_VERSIONS, PhysicalModel
from sonogym.ultrasound.slicer import Slices

#: The learned nets a scene uses by default (shipped net indices).
DEFAULT_LEARNED_NETS = (0, 1, 2, 3, 4)
#: The simulator of an env that names none.
DEFAULT_SIMULATOR = "physical"
#: The ``reference`` model's raw output is shown divided by 20 (``view``), the reference
#: viewer's scale (its observation, raw x 0.02, is dark: about [0, 0.4]).
REFERENCE_VIEW_SCALE = 1 / 20

SIMULATOR_GROUPS = ("MB", "LB")

__all__ = [
    "ALIASES",
    "DEFAULT_LEARNED_NETS",
    "DEFAULT_SIMULATOR",
    "SimulatorOptions",
    "SimulatorSpec",
    "alias_note",
    "build",
    "canonical_name",
    "check_options",
    "get_simulator",
    "identity",
    "is_alias",
    "register",
    "simulator_names",
    "unregister",
]


@dataclass(frozen=True)
class SimulatorOptions:
    """The env options a simulator is built from (each reads those it needs)."""

    learned_nets: tuple = DEFAULT_LEARNED_NETS  # shipped net indices (int) or weight files (str)
    learned_precision: str = "float32"  # "float32", "bfloat16" or "auto"
    gel_depth: float | None = None  # m, coupling gel overriding a model's (None: the model's)


Build = Callable[[Sequence[Any], torch.device, SimulatorOptions], UltrasoundSimulator]


def _display_randomized(sim, slices: Slices, settings: torch.Tensor, probe) -> torch.Tensor:
    return randomized_from_display(sim.simulate(slices).float(), settings, probe)


def _simulate(sim, slices: Slices) -> torch.Tensor:
    return sim.simulate(slices)


@dataclass(frozen=True)
class SimulatorSpec:
    """One simulator: its name, how it is built, how results record it, and what it needs
    (module docstring)."""

    name: str  # ``simulator=`` value
    build: Build
    identity: Callable[[SimulatorOptions], dict[str, Any]]
    summary: str = ""  # one line for help texts and docs
    group: str = "MB"  # "MB" model-based, "LB" learning-based (the paper's table groups)
    draws_net: bool = False  # one net per env, drawn at each reset from ``learned_nets``
    needs_volumes: bool = False  # build reads the patients' whole volumes
    dynamic_range: float = NOMINAL_DYNAMIC_RANGE  # dB its display image spans
    check: Callable[[SimulatorOptions], None] | None = None  # options check, before building
    randomized: Callable[..., torch.Tensor] = field(default=_display_randomized)
    view: Callable[[Any, Slices], torch.Tensor] = field(default=_simulate)

    def __post_init__(self) -> None:
        if self.group not in SIMULATOR_GROUPS:
            raise ValueError(
                f"simulator {self.name!r}: group must be one of {SIMULATOR_GROUPS}, "
                f"got {self.group!r}"
            )


_SIMULATORS: dict[str, SimulatorSpec] = {}


def register(spec: SimulatorSpec) -> SimulatorSpec:
    """Add ``spec``; a name another simulator (or a former name) has is refused."""
    if spec.name in _SIMULATORS or spec.name in ALIASES:
        raise ValueError(f"simulator {spec.name!r} is already registered; choose another name")
    _SIMULATORS[spec.name] = spec
    return spec


def unregister(name: str) -> None:
    """Remove the simulator ``name`` (``KeyError`` if it is not registered)."""
    del _SIMULATORS[name]


def simulator_names() -> tuple[str, ...]:
    """The registered simulators' names, in registration order."""
    return tuple(_SIMULATORS)


def get_simulator(name: str) -> SimulatorSpec:
    """The simulator ``name`` (a former name warns), or a ``ValueError`` listing the known
    ones."""
    spec = _SIMULATORS.get(canonical_name(name))
    if spec is None:
        raise ValueError(f"unknown simulator {name!r}; choose one of {simulator_names()}")
    return spec


def check_options(name: str, options: SimulatorOptions) -> SimulatorSpec:
    """The simulator ``name`` after checking ``options`` for it (clear errors now, not at the
    first image)."""
    spec = get_simulator(name)
    if spec.check is not None:
        spec.check(options)
    return spec


def build(name: str, patients: Sequence[Any], device, options: SimulatorOptions | None = None):
    """The simulator ``name`` built for ``patients`` on ``device``."""
    spec = get_simulator(name)
    return spec.build(list(patients), torch.device(device), options or SimulatorOptions())


def identity(name: str, options: SimulatorOptions | None = None) -> dict[str, Any]:
    """What records the simulator ``name`` in results (its canonical name, never a former)."""
    return get_simulator(name).identity(options or SimulatorOptions())


# ---------------------------------------------------------------- built-in simulators
def _model_based(model_name: str) -> Build:
    def build_model(patients, device, options: SimulatorOptions):
        from sonogym.ultrasound.simulator import ModelBasedSimulator, make_model

        model = make_model(model_name)
        if options.gel_depth is not None:
            model = replace(model, gel_depth=float(options.gel_depth))
        return ModelBasedSimulator(model, device=device)

    return build_model


def _model_identity(model_name: str):
    def model_identity(options: SimulatorOptions) -> dict[str, Any]:
        return {"model": model_name, "version": MODEL_VERSIONS[model_name]}

    return model_identity


def _physical_randomized(sim, slices: Slices, settings: torch.Tensor, probe) -> torch.Tensor:
    """Exact: the settings act on the envelope, before log compression."""
    return randomized_display(sim.simulate_raw(slices), settings, probe, sim.model.gain)


def _reference_view(sim, slices: Slices) -> torch.Tensor:
    return (sim.simulate_raw(slices) * REFERENCE_VIEW_SCALE).clamp_(0, 1)


def _check_precision(options: SimulatorOptions) -> None:
    from sonogym.ultrasound.learned.inference import AUTO, PRECISIONS

    if options.learned_precision not in (AUTO, *PRECISIONS):
        raise ValueError(
            f"learned_precision must be one of {(AUTO, *PRECISIONS)}, "
            f"got {options.learned_precision!r}"
        )


def _check_learned(options: SimulatorOptions) -> None:
    from sonogym.ultrasound.learned.shipped import resolve_nets

    _check_precision(options)
    resolve_nets(options.learned_nets)


def _build_learned(patients, device, options: SimulatorOptions):
    from sonogym.ultrasound.learned.matching import matching_sample
    from sonogym.ultrasound.learned.shipped import resolve_nets
    from sonogym.ultrasound.learned.simulator import LearnedSimulator

    sim = LearnedSimulator(
        resolve_nets(options.learned_nets), device=device, precision=options.learned_precision
    )
    sim.fit_source(matching_sample(patients, device))
    return sim


def _learned_identity(options: SimulatorOptions) -> dict[str, Any]:
    """Each net's name and content digest, and the precision as resolved on this machine."""
    from sonogym.ultrasound.learned.inference import resolve_precision
    from sonogym.ultrasound.learned.shipped import net_digests

    return {
        "model": "learned",
        "nets": net_digests(options.learned_nets),
        "precision": resolve_precision(options.learned_precision),
    }


def _model_spec(model_name: str, summary: str, **declared: Any) -> SimulatorSpec:
    """The entry of the model-based ultrasound model ``model_name`` (``US_MODELS``)."""
    build, ident = _model_based(model_name), _model_identity(model_name)
    return SimulatorSpec(model_name, build=build, identity=ident, summary=summary, **declared)


register(
    _model_spec(
        "physical",
        "the paper's full model-based simulator with literature acoustics",
        dynamic_range=PhysicalModel.dynamic_range,
        randomized=_physical_randomized,
    )
)
register(
    _model_spec(
        "reference",
        "the authors' reference code's CT-mode model, reproduced exactly",
        view=_reference_view,
    )
)
register(
    SimulatorSpec(
        "learned",
        build=_build_learned,
        identity=_learned_identity,
        summary="pix2pix nets (learned_nets), one drawn per env at each reset",
        group="LB",
        draws_net=True,
        needs_volumes=True,
        check=_check_learned,
    )
)
