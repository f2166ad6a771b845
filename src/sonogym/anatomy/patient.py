"""The patient model: a ``Volume`` (CT + labels + frame) with the models derived from it, the
skin surface over the back and the vertebra landmarks, each computed once on first use."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

from sonogym.anatomy.landmarks import Landmarks
from sonogym.anatomy.surface import SkinSurface
from sonogym.anatomy.volume import PatientError, Volume

__all__ = ["Patient", "PatientError"]


@dataclass(frozen=True, eq=False)
class Patient(Volume):
    """CT + labels on one axis-aligned RAS grid (see ``Volume``) and their derived models."""

    @cached_property
    def skin(self) -> SkinSurface:
        """Skin height and inward normals over the back (computed once)."""
        return SkinSurface.from_patient(self)

    @cached_property
    def landmarks(self) -> Landmarks:
        """Vertebra frames and planned pedicle trajectories (computed once)."""
        return Landmarks.from_patient(self)
