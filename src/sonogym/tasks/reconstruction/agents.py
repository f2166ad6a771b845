"""Reconstruction's RL defaults (``TaskSpec.agents`` of ``sonogym.envs.reconstruction``): the
paper's PPO and A2C tables (Tab. ppo_hype, a2c_hype; on this task the submodular PPO and A2C,
the env's reward being the objective's marginal gain) and the settings both share on it.

Units: learning rates per optimiser step; ``rollouts`` in env steps per env between updates;
``timesteps`` in env steps per env.
"""

from sonogym.agents.algorithms.a2c.config import A2CParams
from sonogym.agents.algorithms.ppo.config import PPOParams
from sonogym.agents.task_defaults import CONV3, SMALL_CONV3, CpuRecipe, TrainingDefaults

TRAINING = TrainingDefaults(
    algorithms={
        "ppo": PPOParams(
            rollouts=32, learning_epochs=3, mini_batches=4, learning_rate=3e-4, value_clip=0.1
        ),
        "a2c": A2CParams(rollouts=64, mini_batches=32),
    },
    timesteps=500_000,
    trunks={"paper": CONV3, "small": SMALL_CONV3},
    cpu=CpuRecipe(timesteps=4_000),  # docs/results.md's submodular PPO: 4,000 steps x 64 envs
)
