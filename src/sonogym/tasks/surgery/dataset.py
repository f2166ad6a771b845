"""Surgery's expert datasets (``TaskSpec.dataset`` of ``sonogym.envs.surgery``): the volume's
five elevation slices and the drill tip pose as observation features, the paper's four recipes
(recorded from its wider data-collection starts), and the expert episodes kept (within 2 mm of
the target along the trajectory and 1 mm across it)."""

from sonogym.envs.surgery import DATA_COLLECTION_JOINT_NOISE
from sonogym.imitation.task_datasets import DatasetRecipe, DatasetSpec, Feature

_DATA_COLLECTION_STARTS = {
    "joint_noise": DATA_COLLECTION_JOINT_NOISE,
    "require_free_start": False,
}


def _slice_feature(i: int) -> Feature:
    return Feature(
        f"observation.images.slice_{i}",
        "image",
        (1, 50, 37),
        ("channels", "height", "width"),
        lambda obs, info: obs["image"][:, i : i + 1],
    )


DATASET = DatasetSpec(
    features=(
        *(_slice_feature(i) for i in range(5)),
        Feature(
            "observation.state",
            "float32",
            (7,),
            ("x", "y", "z", "qw", "qx", "qy", "qz"),
            lambda obs, info: obs["pose"],
        ),
    ),
    instruction="perform spine surgery based on ultrasound volume.",  # the reference's
    robot_type="kuka_med14+franka_fr3",
    fps=60,  # the reference's control rate
    # the paper's appendix: wider initial joints, starts that may be unsafe
    recipes=tuple(
        DatasetRecipe(name, n, {**kw, **_DATA_COLLECTION_STARTS})
        for name, n, kw in (
            ("mb", 3536, {"simulator": "physical", "patients": (0,)}),
            ("mb-5-patients", 1476, {"simulator": "physical", "patients": (0, 1, 2, 3, 4)}),
            ("lb", 2052, {"simulator": "learned", "learned_nets": (0,)}),
            ("lb-4-nets", 2692, {"simulator": "learned", "learned_nets": (0, 1, 2, 3)}),
        )
    ),
    success=lambda m: (m["insertion_error_mm"] < 2.0) & (m["side_error_mm"] < 1.0),
)
