"""A patient's volumes: CT in Hounsfield units, a label map, and the frame that places them.

Frames (docs/design.md): the patient frame {P} is RAS+ in metres (+x toward the patient's right,
+y anterior, +z superior). Volumes are stored in canonical RAS voxel order, axis-aligned: voxel
(i, j, k) sits at ``origin + spacing * (i, j, k)``. The patient lies prone, so the back's skin is
the smallest-y body surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from sonogym.anatomy.labels import label_id


class PatientError(ValueError):
    """A patient's data is malformed; the message says what and how to fix it."""


#: Values of a volume checked at a time by ``_all_finite`` (16 MB of float32).
_FINITE_CHUNK = 1 << 22


def _all_finite(t: torch.Tensor) -> bool:
    """Whether every value of ``t`` (3-D) is finite, checked a slab of x planes at a time:
    ``torch.isfinite`` of a whole volume makes ~7 bytes per voxel of temporaries (an absolute
    value and three masks: about 210 MB for a phantom at 1 mm)."""
    step = max(1, _FINITE_CHUNK // max(1, math.prod(t.shape[1:])))
    return all(bool(torch.isfinite(s).all()) for s in t.split(step))


class AxisAlignedGrid:
    """Spacing and origin of a grid whose ``affine`` (4, 4) is diagonal (canonical RAS)."""

    affine: np.ndarray

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size (3,) in metres."""
        return np.diag(self.affine)[:3].copy()

    @property
    def origin(self) -> np.ndarray:
        """Patient-frame position (3,) of voxel (0, 0, 0), metres."""
        return self.affine[:3, 3].copy()


@dataclass(frozen=True, eq=False)
class Volume(AxisAlignedGrid):
    """CT + labels on one axis-aligned RAS grid (what the skin and landmark models are built
    from; ``sonogym.anatomy.Patient`` adds them).

    Attributes:
        ct: (X, Y, Z) float32 tensor, Hounsfield units.
        labels: (X, Y, Z) uint8 tensor, ids of ``sonogym.anatomy.labels`` (0 = outside the body).
        affine: (4, 4) float64 array, voxel index -> patient frame in metres. Diagonal with
            positive spacing (canonical RAS, axis-aligned); loaders resample anything else.
        name: a short identifier ("phantom-3", "s0010").
        meta: free-form provenance (seed, generator parameters, source folder, ...).
    """

    ct: torch.Tensor
    labels: torch.Tensor
    affine: np.ndarray
    name: str = "patient"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        ct, labels = self.ct, self.labels
        if not isinstance(ct, torch.Tensor) or not isinstance(labels, torch.Tensor):
            raise PatientError("Patient.ct and Patient.labels must be torch tensors")
        if ct.ndim != 3:
            raise PatientError(f"{self.name}: CT must be 3-D, got shape {tuple(ct.shape)}")
        if labels.shape != ct.shape:
            raise PatientError(
                f"{self.name}: label map shape {tuple(labels.shape)} differs from CT shape "
                f"{tuple(ct.shape)}; resample the labels onto the CT grid"
            )
        if ct.dtype != torch.float32:
            raise PatientError(f"{self.name}: CT must be float32 HU, got {ct.dtype}")
        if labels.dtype != torch.uint8:
            raise PatientError(f"{self.name}: labels must be uint8, got {labels.dtype}")
        if not _all_finite(ct):
            raise PatientError(
                f"{self.name}: CT contains NaN or inf; replace them (e.g. by -1024 HU) first"
            )
        aff = np.asarray(self.affine, dtype=np.float64)
        if aff.shape != (4, 4):
            raise PatientError(f"{self.name}: affine must be 4x4, got {aff.shape}")
        lin = aff[:3, :3]
        if np.abs(lin - np.diag(np.diag(lin))).max() > 1e-9 or (np.diag(lin) <= 0).any():
            raise PatientError(
                f"{self.name}: affine must be axis-aligned RAS with positive spacing; load files "
                "through sonogym.anatomy.load_totalsegmentator, which reorients and resamples"
            )
        object.__setattr__(self, "affine", aff)

    # ----------------------------------------------------------------- geometry
    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.ct.shape)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) min and max voxel-centre coordinates in metres."""
        lo = self.origin
        return np.stack([lo, lo + self.spacing * (np.array(self.shape) - 1)])

    def voxel_to_world(self, ijk: torch.Tensor) -> torch.Tensor:
        """(..., 3) voxel indices -> patient-frame metres."""
        sp = torch.as_tensor(self.spacing, dtype=ijk.dtype, device=ijk.device)
        org = torch.as_tensor(self.origin, dtype=ijk.dtype, device=ijk.device)
        return org + ijk * sp

    def world_to_voxel(self, p: torch.Tensor) -> torch.Tensor:
        """(..., 3) patient-frame metres -> fractional voxel indices."""
        sp = torch.as_tensor(self.spacing, dtype=p.dtype, device=p.device)
        org = torch.as_tensor(self.origin, dtype=p.dtype, device=p.device)
        return (p - org) / sp

    def world_to_voxel_np(self, p: np.ndarray) -> np.ndarray:
        """NumPy version of :meth:`world_to_voxel`."""
        return (np.asarray(p) - self.origin) / self.spacing

    def mask(self, *names_or_ids: str | int) -> torch.Tensor:
        """Boolean mask of the union of the given structures."""
        ids = torch.tensor([label_id(n) for n in names_or_ids], dtype=torch.uint8)
        return torch.isin(self.labels, ids)

    def has(self, name_or_id: str | int) -> bool:
        """Whether the label map contains at least one voxel of a structure."""
        return bool((self.labels == label_id(name_or_id)).any())

    @property
    def nbytes(self) -> int:
        """Bytes held by the volumes."""
        return self.ct.numel() * self.ct.element_size() + self.labels.numel()
