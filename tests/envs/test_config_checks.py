"""Env options are checked where they enter, the config: no NaN or inf reaches a reward, an
integer option is never truncated."""

from __future__ import annotations

import math

import pytest

from sonogym.envs.registry import env_config, get_task, make_vec

#: one float option per task (a reward weight) and the task's action tuple
WEIGHTS = {"navigation": "w1", "reconstruction": "w2", "surgery": "w4"}


@pytest.mark.parametrize("task", list(WEIGHTS))
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, float("1e309"), True])
def test_every_task_config_refuses_a_number_that_is_not_finite(task, bad):
    cls, weight = get_task(task).config_cls, WEIGHTS[task]
    with pytest.raises(ValueError, match=rf"{cls.__name__}\.{weight} must be a finite number"):
        cls(**{weight: bad})
    scale = list(cls().action_scale)
    scale[1] = bad
    with pytest.raises(ValueError, match=r"action_scale\[1\] must be a finite number"):
        cls(action_scale=tuple(scale))


@pytest.mark.parametrize("task", list(WEIGHTS))
def test_integer_options_take_integers_only_and_are_never_truncated(task):
    cls = get_task(task).config_cls
    for bad in (2.5, math.inf, float("1e309"), "20"):
        with pytest.raises(ValueError, match="episode_length must be an integer"):
            cls(episode_length=bad)
    cfg = cls(episode_length=20.0)  # an integral float is that integer
    assert cfg.episode_length == 20 and type(cfg.episode_length) is int


def test_an_overflowing_episode_length_is_a_named_error_not_a_traceback():
    # 1e309 reads as inf: int(inf) raised OverflowError inside the env's constructor
    with pytest.raises(ValueError, match="episode_length must be an integer, got inf"):
        make_vec("navigation", 1, episode_length=float("1e309"), phantom_spacing=0.002)


def test_env_config_names_unknown_options_and_refused_values_as_value_errors():
    with pytest.raises(ValueError, match=r"navigation env options: unknown .*'bogus'.*'w1'"):
        env_config("navigation", {"bogus": 1})
    with pytest.raises(ValueError, match="episode_length must be >= 1"):
        env_config("surgery", {"episode_length": -1})
    assert env_config("surgery", {"episode_length": 7}).episode_length == 7
