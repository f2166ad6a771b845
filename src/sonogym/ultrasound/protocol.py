"""The interface every ultrasound simulator implements (``ModelBasedSimulator``,
``LearnedSimulator``)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch

from sonogym.ultrasound.slicer import Slices


@runtime_checkable
class UltrasoundSimulator(Protocol):
    """Turns CT + label slices into B-mode images.

    ``simulate(slices)`` returns (N, E, H, W) float32 images in [0, 1] on the slices' device,
    one per env and elevation slice; it must be deterministic for a given pose (speckle fixed in
    patient space) and batch-independent (an env's image does not depend on the other envs).
    """

    def simulate(self, slices: Slices) -> torch.Tensor: ...
