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

    Everything a simulator needs about an env travels in its row of ``slices``: the speckle
    seed of its patient (``Slices.seed``) and, for the learned simulator, the net that images
    it (``Slices.net_index``, which model-based simulators ignore). So one call serves every
    simulator, and a caller never branches on which one it holds.
    """

    def simulate(self, slices: Slices) -> torch.Tensor: ...
