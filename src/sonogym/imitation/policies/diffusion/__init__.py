"""Diffusion Policy: ``configuration`` (``DiffusionConfig``) and ``modeling``
(``DiffusionPolicy``)."""

from sonogym.imitation.policies.diffusion.configuration import DiffusionConfig
from sonogym.imitation.policies.diffusion.modeling import DiffusionPolicy

__all__ = ["DiffusionConfig", "DiffusionPolicy"]
