"""ACT, the Action Chunking Transformer: ``configuration`` (``ACTConfig``) and ``modeling``
(``ACTPolicy``)."""

from sonogym.imitation.policies.act.configuration import ACTConfig
from sonogym.imitation.policies.act.modeling import ACTPolicy

__all__ = ["ACTConfig", "ACTPolicy"]
