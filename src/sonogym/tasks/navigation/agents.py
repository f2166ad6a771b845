"""Navigation's RL defaults (``TaskSpec.agents`` of ``sonogym.envs.navigation``): the paper's
PPO and A2C tables (Tab. ppo_hype, a2c_hype) and the settings both share on this task.

Units: learning rates per optimiser step; ``rollouts`` in env steps per env between updates;
``timesteps`` in env steps per env; scales unitless factors.
"""

from sonogym.agents.algorithms.a2c.config import A2CParams
from sonogym.agents.algorithms.ppo.config import PPOParams
from sonogym.agents.task_defaults import CONV4, SMALL_CONV4, CpuRecipe, TrainingDefaults

TRAINING = TrainingDefaults(
    algorithms={
        "ppo": PPOParams(
            rollouts=32, learning_epochs=5, mini_batches=32, learning_rate=1e-4, value_clip=0.2
        ),
        "a2c": A2CParams(rollouts=16, mini_batches=32),
    },
    timesteps=500_000,
    trunks={"paper": CONV4, "small": SMALL_CONV4},
    # the single-phantom PPO of docs/results.md: 9,024 steps x 64 envs, ~45 CPU min
    cpu=CpuRecipe(timesteps=9_024),
    image_height=200,  # px of depth of the 200 x 150 image
    # m -> per 10 mm: order 1 over the memory's window, up to ~15 from the scan's caudal end
    obs_scales_by_mode={"us_memory": {"motion": 100.0}, "us_scan": {"motion": 100.0}},
)
