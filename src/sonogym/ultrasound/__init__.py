"""Ultrasound: probe geometry, batched slicer, tissue tables and simulators.

Typical use::

    slicer = Slicer(patients, ProbeGeometry.linear_2d())
    sim = ModelBasedSimulator("physical")          # or "reference"
    images = sim.simulate(slicer(pos, rot))        # (N, E, H, W) in [0, 1]

Envs pick a simulator by name from the registry (``sonogym.ultrasound.registry``):
``get_simulator("learned")``; ``registry.register`` adds one of your own.
"""

from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.ultrasound.protocol import UltrasoundSimulator
from sonogym.ultrasound.registry import (
    SimulatorOptions,
    SimulatorSpec,
    get_simulator,
    simulator_names,
)
from sonogym.ultrasound.simulator import (
    US_MODELS,
    ModelBasedSimulator,
    PhysicalModel,
    ReferenceModel,
    make_model,
)
from sonogym.ultrasound.slicer import Slicer, Slices
from sonogym.ultrasound.tissues import (
    GEL,
    PHYSICAL_LABEL_TISSUE,
    PHYSICAL_TISSUES,
    REFERENCE_LABEL_TISSUE,
    REFERENCE_TISSUES,
    Tissue,
    TissueTable,
    physical_table,
    reference_table,
)

__all__ = [
    "GEL",
    "PHYSICAL_LABEL_TISSUE",
    "PHYSICAL_TISSUES",
    "REFERENCE_LABEL_TISSUE",
    "REFERENCE_TISSUES",
    "ModelBasedSimulator",
    "PhysicalModel",
    "ProbeGeometry",
    "SimulatorOptions",
    "SimulatorSpec",
    "Slicer",
    "Slices",
    "ReferenceModel",
    "Tissue",
    "TissueTable",
    "US_MODELS",
    "UltrasoundSimulator",
    "get_simulator",
    "make_model",
    "physical_table",
    "simulator_names",
    "reference_table",
]
