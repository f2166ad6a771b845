"""Batched Gymnasium environments of the three tasks, registered on ``import sonogym``.

``gymnasium.make_vec("SonoGym/Navigation-v0", num_envs=128, **options)`` gives the native
batched env (torch tensors, SAME_STEP autoreset); ``gymnasium.make(...)`` one env with NumPy I/O.
"""

from __future__ import annotations

import gymnasium as gym

#: Registered task ids -> module that implements them.
TASKS: dict[str, str] = {
    "SonoGym/Navigation-v0": "sonogym.envs.navigation",
    "SonoGym/Reconstruction-v0": "sonogym.envs.reconstruction",
    "SonoGym/Surgery-v0": "sonogym.envs.surgery",
}


def register_envs() -> None:
    """Register every SonoGym task with Gymnasium (idempotent)."""
    for env_id, module in TASKS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=f"{module}:make_single",
            vector_entry_point=f"{module}:{_vector_class(env_id)}",
            disable_env_checker=False,
        )


def _vector_class(env_id: str) -> str:
    return env_id.split("/")[1].split("-")[0] + "Env"


register_envs()
