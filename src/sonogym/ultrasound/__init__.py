"""Ultrasound: probe geometry, batched slicer, tissue tables and simulators.

Typical use::

    slicer = Slicer(patients, ProbeGeometry.linear_2d())
    sim = ModelBasedSimulator("physical")          # or "sonogym"
    images = sim.simulate(slicer(pos, rot))        # (N, E, H, W) in [0, 1]
"""

from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.ultrasound.protocol import UltrasoundSimulator
from sonogym.ultrasound.simulator import (
    US_MODELS,
    ModelBasedSimulator,
    PhysicalModel,
    SonoGymModel,
    deprecated_module_attribute,
    make_model,
)
from sonogym.ultrasound.slicer import Slicer, Slices
from sonogym.ultrasound.tissues import (
    GEL,
    PHYSICAL_LABEL_TISSUE,
    PHYSICAL_TISSUES,
    SONOGYM_LABEL_TISSUE,
    SONOGYM_TISSUES,
    Tissue,
    TissueTable,
    physical_table,
    sonogym_table,
)

__all__ = [
    "GEL",
    "PHYSICAL_LABEL_TISSUE",
    "PHYSICAL_TISSUES",
    "SONOGYM_LABEL_TISSUE",
    "SONOGYM_TISSUES",
    "ModelBasedSimulator",
    "PhysicalModel",
    "ProbeGeometry",
    "Slicer",
    "Slices",
    "SonoGymModel",
    "Tissue",
    "TissueTable",
    "US_MODELS",
    "UltrasoundSimulator",
    "make_model",
    "physical_table",
    "sonogym_table",
]


def __getattr__(name: str) -> dict[str, type]:
    return deprecated_module_attribute(__name__, name)
