"""Learning-based ultrasound simulation (pix2pix) at inference: networks, histogram matching,
degradation, generator checkpoints, the shipped nets and ``LearnedSimulator``. Training lives
in ``sonogym.learned_training``. See docs/learned.md."""

from sonogym.ultrasound.learned.augment import down_up, random_down_up
from sonogym.ultrasound.learned.histogram import CT_WINDOW_HU, HistogramReference, window_ct
from sonogym.ultrasound.learned.networks import PatchDiscriminator, UNet, UNetConfig

__all__ = [
    "CT_WINDOW_HU",
    "HistogramReference",
    "PatchDiscriminator",
    "UNet",
    "UNetConfig",
    "down_up",
    "random_down_up",
    "window_ct",
]


def __getattr__(name: str):
    # lazy: the simulator pulls in the slicer
    if name == "LearnedSimulator":
        from sonogym.ultrasound.learned.simulator import LearnedSimulator

        return LearnedSimulator
    raise AttributeError(name)
