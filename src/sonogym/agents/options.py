"""The settings of a training run that ``sonogym train`` and ``sonogym sweep`` share, in one
dataclass (``RunOptions``): each field is one flag of both commands (``obs_downsample`` is
``--obs-downsample``) and its ``help`` metadata the flag's help text, so the two commands
cannot drift apart. A field left None was not given: the task's defaults, then the device
preset decide (``configs.resolve_train_config``).

Adding a setting to both commands: add a field here (type, None default, help) and read it
where the run is resolved.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from sonogym.agents.presets import PRESETS
from sonogym.envs.options import parse_learned_nets, parse_patients


def _flag(help: str) -> Any:
    """A field given on the command line: None until given; ``help`` is its help text."""
    return field(default=None, metadata={"help": help})


@dataclass(frozen=True)
class RunOptions:
    """A training run's shared command-line settings (None: not given)."""

    preset: str | None = _flag(
        "Device preset for envs, network size, image downsampling and threads: auto "
        "(default: paper on CUDA, cpu otherwise), cpu or paper."
    )
    envs: int | None = _flag("Parallel envs (default: the preset's).")
    steps: int | None = _flag("Env steps per env in total (default: the paper's).")
    net: str | None = _flag(
        "Network size: paper, small or lean (small convs, [256, 128, 64] ReLU trunk; surgery "
        "state runs on a CPU). Default: the preset's."
    )
    obs_downsample: int | None = _flag("Average-pool image observations by this factor.")
    obs_mode: str | None = _flag(
        "Observation: the task's default (images), or 'state' (the privileged state), 'ct' / "
        "'labels' (navigation, surgery), 'us_heading' (navigation: image + the probe's yaw), "
        "'us_memory' (navigation: us_heading + the image 30 steps back and the motion since), "
        "'us_scan' (navigation: us_memory + the image where the probe was most caudal)."
    )
    simulator: str | None = _flag(
        "Ultrasound simulator: physical, reference, learned or another registered one."
    )
    learned_nets: str | None = _flag(
        "With --simulator learned: comma-separated shipped net indices (0-4) and/or "
        "generator.pt paths, e.g. 0,1,2,3 (default: all five)."
    )
    patients: list[str] | None = _flag(
        "Phantom seed, seed range A-B (inclusive) or TotalSegmentator folder; repeatable "
        "(default 0)."
    )
    phantom_spacing: float | None = _flag("Phantom voxel size in mm (default 1).")
    threads: int | None = _flag("torch CPU threads (default: the preset's).")
    device: str | None = _flag("cpu or cuda[:i] (default cpu).")

    #: integer settings that must be >= 1 when given
    COUNTS = ("steps", "envs", "obs_downsample", "threads")

    def check(self) -> None:
        """Refuse, naming the flag, a count below 1 and an unknown preset: nothing given is
        silently defaulted."""
        for name in self.COUNTS:
            v = getattr(self, name)
            if v is not None and v < 1:
                raise ValueError(f"{flag(name)} must be a positive integer, got {v}")
        if self.preset is not None and self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; choose from {list(PRESETS)}")

    def given(self) -> list[str]:
        """The flags given, in field order."""
        return [flag(f.name) for f in dataclasses.fields(self) if getattr(self, f.name) is not None]

    def patient_specs(self) -> tuple[int | str, ...] | None:
        """``--patients`` as the env's ``patients`` option (None: not given)."""
        return parse_patients(self.patients)

    def scene_kwargs(self) -> dict[str, Any]:
        """The env options of ``--phantom-spacing`` (mm -> m), ``--obs-mode`` and
        ``--learned-nets``, those given; ``--patients`` and ``--simulator`` are apart
        (``patient_specs``, ``simulator``): a protocol may replace them."""
        kw: dict[str, Any] = {}
        if self.phantom_spacing is not None:
            kw["phantom_spacing"] = self.phantom_spacing * 1e-3
        if self.obs_mode is not None:
            kw["obs_mode"] = self.obs_mode
        if self.learned_nets:
            kw["learned_nets"] = parse_learned_nets(self.learned_nets)
        return kw

    def env_kwargs(self) -> dict[str, Any]:
        """Every env option these settings give (only those given)."""
        kw = self.scene_kwargs()
        if self.simulator is not None:
            kw["simulator"] = self.simulator
        if self.patients:
            kw["patients"] = self.patient_specs()
        return kw

    def train_kwargs(self) -> dict[str, Any]:
        """``resolve_train_config`` / ``sweep`` keywords of the run settings (preset, envs,
        steps, net, obs_downsample, threads, device; None: not given)."""
        names = ("preset", "envs", "steps", "net", "obs_downsample", "threads", "device")
        return {k: getattr(self, k) for k in names}


def flag(name: str) -> str:
    """The command-line flag of field ``name``: ``obs_downsample`` -> ``--obs-downsample``."""
    return "--" + name.replace("_", "-")
