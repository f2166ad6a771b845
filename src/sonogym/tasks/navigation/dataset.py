"""Navigation's expert datasets (``TaskSpec.dataset`` of ``sonogym.envs.navigation``): the
ultrasound image as the one observation feature, the paper's three recipes, and the expert
episodes kept (within 5 mm and 5 deg of the goal)."""

from sonogym.imitation.task_datasets import DatasetRecipe, DatasetSpec, Feature

DATASET = DatasetSpec(
    features=(
        Feature(
            "observation.images.us",
            "image",
            (1, 200, 150),
            ("channels", "height", "width"),
            lambda obs, info: obs,
        ),
    ),
    instruction="Navigate the ultrasound probe to the transverse view above L4.",
    robot_type="kuka_med14",
    fps=60,  # the reference's control rate
    recipes=(  # the paper's appendix Table "Number of episodes for expert datasets"
        DatasetRecipe("mb", 2052, {"simulator": "physical", "patients": (0,)}),
        DatasetRecipe("lb", 1869, {"simulator": "learned", "learned_nets": (0,)}),
        DatasetRecipe("lb-4-nets", 954, {"simulator": "learned", "learned_nets": (0, 1, 2, 3)}),
    ),
    success=lambda m: (m["position_error_mm"] < 5.0) & (m["angle_error_deg"] < 5.0),
)
