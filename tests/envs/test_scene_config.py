"""The scene settings every task config shares (``SceneConfig``): one definition, the same
checks and normalisation for each task, every field still a flat ``make_vec`` keyword."""

import dataclasses

import pytest

from sonogym.envs.registry import TASKS
from sonogym.envs.scene_config import SceneConfig

SHARED = [f.name for f in dataclasses.fields(SceneConfig)]


@pytest.mark.parametrize("spec", TASKS.values(), ids=lambda s: s.name)
def test_every_task_config_is_a_scene_config(spec):
    cls = spec.config_cls
    assert issubclass(cls, SceneConfig)
    names = [f.name for f in dataclasses.fields(cls)]
    assert names[: len(SHARED)] == SHARED  # shared fields first, flat keywords
    cfg = cls(patients=3, learned_nets=[0, 2], phantom_spacing=0.002)
    assert cfg.patients == (3,) and cfg.learned_nets == (0, 2)
    assert cfg.obs_mode in cls.obs_modes and cfg.obs_mode == spec.default_obs_mode


@pytest.mark.parametrize("spec", TASKS.values(), ids=lambda s: s.name)
def test_shared_checks_name_the_field(spec):
    cls = spec.config_cls
    with pytest.raises(ValueError, match="obs_mode 'sonar' is not one of"):
        cls(obs_mode="sonar")
    with pytest.raises(ValueError, match="episode_length must be >= 1"):
        cls(episode_length=0)
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.phantom_spacing must be a finite"):
        cls(phantom_spacing=float("nan"))


def test_task_defaults_kept():
    """Paper episode lengths: navigation and reconstruction 300, surgery 600 steps."""
    lengths = {s.name: s.config_cls().episode_length for s in TASKS.values()}
    assert lengths == {"navigation": 300, "reconstruction": 300, "surgery": 600}
