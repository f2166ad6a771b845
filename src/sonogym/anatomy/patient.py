"""The patient model: a ``Volume`` (CT + labels + frame) with the models derived from it, the
skin surface over the back and the vertebra landmarks, each computed once on first use; and
``PatientModel``, what a built env keeps of a patient once its imaging holds its own compact
copy of the volumes."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from sonogym.anatomy.landmarks import Landmarks
from sonogym.anatomy.surface import SkinSurface
from sonogym.anatomy.volume import AxisAlignedGrid, PatientError, Volume

__all__ = ["Patient", "PatientError", "PatientModel"]


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

    def adopt(self, model: PatientModel) -> None:
        """Take the skin and landmarks of ``model``, derived earlier from these same volumes
        (a reload of the same patient), instead of computing them again."""
        if model.shape != self.shape or not np.array_equal(model.affine, self.affine):
            raise PatientError(
                f"{self.name}: cannot adopt the models of {model.name}, another grid "
                f"({model.shape} voxels) than this patient's ({self.shape})"
            )
        self.__dict__["skin"] = model.skin  # where cached_property keeps its value
        self.__dict__["landmarks"] = model.landmarks

    def model(self) -> PatientModel:
        """This patient without its CT and label volumes (skin and landmarks computed now)."""
        return PatientModel(
            self.name, self.affine.copy(), self.shape, self.skin, self.landmarks, dict(self.meta)
        )


@dataclass(frozen=True, eq=False)
class PatientModel(AxisAlignedGrid):
    """A patient's grid, skin surface and landmarks, without the volumes: what a built env
    keeps (``PatientScene.release_volumes``), some 1.5 MB instead of the CT's and labels'
    5 bytes per voxel (117 MB for a phantom at 1 mm). ``ct`` and ``labels`` raise an error
    that says where to get them."""

    name: str
    affine: np.ndarray
    shape: tuple[int, int, int]
    skin: SkinSurface
    landmarks: Landmarks
    meta: dict = field(default_factory=dict)

    @property
    def ct(self):
        raise AttributeError(self._released("ct"))

    @property
    def labels(self):
        raise AttributeError(self._released("labels"))

    def _released(self, what: str) -> str:
        return (
            f"{self.name}: an env keeps no full {what} volume once its slicer is built (memory); "
            "load the patient with sonogym.envs.patients.resolve_patients (or "
            "sonogym.anatomy.load_phantom / load_totalsegmentator) for its volumes"
        )
