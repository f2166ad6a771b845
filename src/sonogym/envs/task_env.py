"""The base of every task's batched env: its config made from keywords, and the memory it
will take checked against the machine before any patient loads."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sonogym.envs.base import TorchVectorEnv, make_config
from sonogym.envs.footprint import check_env_fits

if TYPE_CHECKING:
    from sonogym.envs.spec import TaskSpec


class TaskEnv(TorchVectorEnv):
    """A task's ``TorchVectorEnv``: ``self.cfg`` is ``spec.config_cls`` made from ``kwargs``
    (``make_config``: unknown keys are refused, naming them); an env too big for the
    machine's memory or the phantom cache's disk is refused here, before anything loads."""

    def __init__(self, num_envs: int, spec: TaskSpec, kwargs: dict[str, Any]) -> None:
        cfg = make_config(spec.config_cls, kwargs)
        super().__init__(num_envs, cfg.device, cfg.episode_length)
        check_env_fits(spec.name, spec.memory, num_envs, cfg)
        self.cfg = cfg
