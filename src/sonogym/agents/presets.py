"""Device presets for training: how many envs, which network size, how much to downsample
images and how many torch threads fit the machine a run is on.

Presets set only these four; the task's own settings (the paper's hyperparameter tables,
initial exploration, input scaling, and the algorithm configs and env options a task may keep
for the ``cpu`` preset: ``TrainingDefaults.cpu``) come from the task's agents module
(``sonogym.tasks.<task>.agents``). A run's settings resolve in one order: the task's
defaults, then the preset, then explicit options.

* ``paper``: the paper's configuration (128 envs, the paper's conv trunks, full-resolution
  images, torch's default threads) — meant for a GPU.
* ``cpu``: what trains in minutes on a small CPU (measured on 2 cores): 64 envs, the small
  trunks, images average-pooled to about 50 px of depth (navigation 200 x 150 -> 50 x 37; the
  surgery volume is 50 px deep already), and one torch thread per process on machines with at
  most 2 cores (a second intra-op thread slowed everything several-fold when the other core was
  busy), else up to 4.
* ``auto`` (default): ``paper`` where the run's device is a CUDA GPU, ``cpu`` otherwise.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

PRESETS = ("auto", "cpu", "paper")
#: image depth (px) the ``cpu`` preset pools images down to
CPU_IMAGE_DEPTH = 50


@dataclass(frozen=True)
class Preset:
    """The resolved preset: its name and the four settings it fixes."""

    name: str  # "cpu" or "paper" ("auto" resolved)
    num_envs: int
    net: str  # conv trunk size, a key of the task's ``trunks``
    image_depth: int | None  # px the images are pooled to (None: full resolution)
    threads: int | None  # torch CPU threads (None: torch's default)

    def obs_downsample(self, image_height: int | None) -> int:
        """The integer pooling factor for images ``image_height`` px deep (1: none)."""
        if self.image_depth is None or not image_height:
            return 1
        return max(1, image_height // self.image_depth)


def cpu_threads(cores: int | None = None) -> int:
    """Torch threads per training process on a CPU machine with ``cores`` cores."""
    cores = cores or os.cpu_count() or 1
    return 1 if cores <= 2 else min(cores, 4)


def resolve_preset(name: str, device: str = "cpu", cores: int | None = None) -> Preset:
    """The preset ``name`` for a run on ``device``; ``auto`` picks by device."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {list(PRESETS)}")
    if name == "auto":
        name = "paper" if str(device).startswith("cuda") else "cpu"
    if name == "paper":
        return Preset("paper", num_envs=128, net="paper", image_depth=None, threads=None)
    return Preset("cpu", num_envs=64, net="small", image_depth=CPU_IMAGE_DEPTH,
                  threads=cpu_threads(cores))  # fmt: skip
