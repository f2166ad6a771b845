"""What every task's env config shares: the patients, the ultrasound simulator, the
observation, the device and the episode length (``SceneConfig``).

Each task config (``NavigationConfig``, ``ReconstructionConfig``, ``SurgeryConfig``) subclasses
it and adds its own fields, so every field stays a flat ``gymnasium.make`` / ``make_vec``
keyword and a ``sonogym train --env-option KEY=VALUE`` key. A subclass redeclares a field only
to change its default or narrow its type (``obs_mode``, surgery's ``episode_length``), and sets
``obs_modes`` to the observation modes it knows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from sonogym.envs.base import check_number_fields
from sonogym.envs.imaging import learned_nets_tuple
from sonogym.ultrasound.compression import MAX_CONTACT_FORCE
from sonogym.ultrasound.learned.inference import resolve_precision
from sonogym.ultrasound.randomization import ImagingRandomization, imaging_ranges
from sonogym.ultrasound.registry import DEFAULT_SIMULATOR, get_simulator


@dataclass(frozen=True)
class SceneConfig:
    """The settings every task's scene has (paper defaults). Every field is a ``make_vec``
    keyword; ``__post_init__`` checks them and normalises ``patients`` and ``learned_nets``
    to tuples. Subclasses call ``super().__post_init__()`` before their own checks."""

    #: the ``obs_mode`` values the task knows (set by each task config)
    obs_modes: ClassVar[tuple[str, ...]] = ()

    patients: tuple = (0,)  # phantom seeds (int) and/or TotalSegmentator folders (str)
    phantom_spacing: float = 0.001  # m, voxel size of phantoms and resampled folders
    # a registered simulator (``sonogym.ultrasound.registry``): "physical", "reference",
    # "learned" or one of your own; a former name is replaced by its current one (warned)
    simulator: str = DEFAULT_SIMULATOR
    learned_nets: tuple = (0, 1, 2, 3, 4)  # simulator="learned": shipped nets (int), files (str)
    # simulator="learned": the nets' working precision, "float32" (the reference), "bfloat16"
    # (~2x faster on a CPU with native bfloat16) or "auto": bfloat16 where the CPU has it
    learned_precision: str = "auto"
    crop_to_reach: bool = True  # images slice only the region the probe can reach (memory)
    imaging_randomization: bool | ImagingRandomization = False  # per-episode display settings
    # (gain, range, TGC, attenuation, speckle, depth) for training; True: the documented ranges
    obs_mode: str = "us"  # one of ``obs_modes``
    device: str = "cpu"  # torch device of every tensor the env returns
    episode_length: int = 300  # control steps (paper: navigation and reconstruction)
    target_vertebra: str = "L4"  # the vertebra the task is about (goal, surface, pedicle)
    # N, 0 ... 30: the probe presses the skin this hard and the soft tissue under it
    # compresses (``sonogym.ultrasound.compression``); 0: static tissue, the paper's images.
    # With ``force_action`` (navigation, reconstruction) the force each episode starts at
    contact_force: float = 0.0
    force_limit: float = 20.0  # N: info["force_cost"] is 1 where the applied force exceeds it

    def __post_init__(self) -> None:
        check_number_fields(self)
        if not 0.0 <= self.contact_force <= MAX_CONTACT_FORCE:
            raise ValueError(
                f"contact_force must be between 0 and {MAX_CONTACT_FORCE:g} N, got "
                f"{self.contact_force!r}; 0 keeps the tissue static"
            )
        if self.force_limit < 0:
            raise ValueError(f"force_limit must be >= 0 N, got {self.force_limit!r}")
        object.__setattr__(
            self, "imaging_randomization", imaging_ranges(self.imaging_randomization) or False
        )
        if self.obs_mode not in self.obs_modes:
            raise ValueError(f"obs_mode {self.obs_mode!r} is not one of {self.obs_modes}")
        if self.episode_length < 1:
            raise ValueError("episode_length must be >= 1")
        if isinstance(self.patients, int | str):
            object.__setattr__(self, "patients", (self.patients,))
        object.__setattr__(self, "patients", tuple(self.patients))
        object.__setattr__(self, "learned_nets", learned_nets_tuple(self.learned_nets))
        # an unknown name is refused naming the registered ones; a former name is renamed
        object.__setattr__(self, "simulator", get_simulator(self.simulator).name)
        # the precision a run uses, as it records it (an "auto" resolved on this machine)
        object.__setattr__(
            self,
            "learned_precision",
            resolve_precision(self.learned_precision, "learned_precision"),
        )

    @property
    def compresses_tissue(self) -> bool:
        """Whether the probe's contact force compresses the tissue (a force, or a force
        action): the images then differ from the static model's."""
        return self.contact_force > 0 or bool(getattr(self, "force_action", False))
