"""Env options are checked where they enter, the config: no NaN or inf reaches a reward, an
integer option is never truncated, and a run too large for the machine is refused, with the
estimate and the limit, before a patient is loaded or a phantom built."""

from __future__ import annotations

import math

import pytest

from sonogym.envs import footprint
from sonogym.envs.registry import env_config, get_task, make_vec
from sonogym.memory import ResourceLimitError

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


def _no_patient_loads(monkeypatch):
    from sonogym.envs import patients

    def refuse(*a, **k):
        raise AssertionError("a patient was loaded before the size check")

    monkeypatch.setattr(patients, "_load", refuse)


def test_an_env_too_large_for_memory_is_refused_with_the_figure_and_the_limit(monkeypatch):
    _no_patient_loads(monkeypatch)
    monkeypatch.setattr(footprint, "free_memory", lambda device: 4 * 2**30)
    mem = get_task("navigation").memory
    need = footprint.env_memory(mem, 100_000, 1, 1e-3)
    # the measured constants: 0.88 MB per env dominates 100,000 envs
    assert need == pytest.approx(100_000 * 0.88e6, rel=0.01)
    with pytest.raises(ResourceLimitError) as e:
        make_vec("navigation", 100_000)
    msg = str(e.value)
    assert f"{need / 2**30:.2f} GiB of memory" in msg and "(3.20 GiB)" in msg
    assert "100000 envs over 1 patients" in msg and "fewer envs" in msg


def test_patients_count_in_the_memory_estimate_and_scale_with_their_voxels(monkeypatch):
    _no_patient_loads(monkeypatch)
    monkeypatch.setattr(footprint, "free_memory", lambda device: 8 * 2**30)
    mem = get_task("surgery").memory
    one, many = (footprint.env_memory(mem, 4, p, 1e-3) for p in (1, 101))
    assert many - one == pytest.approx(100 * mem.per_patient)
    at_2mm = footprint.env_memory(mem, 4, 101, 2e-3) - footprint.env_memory(mem, 4, 1, 2e-3)
    fixed = footprint.PATIENT_FIXED
    assert at_2mm == pytest.approx(100 * (fixed + (mem.per_patient - fixed) / 8))
    with pytest.raises(ResourceLimitError, match="over 101 patients at 1 mm"):
        make_vec("surgery", 4, patients=tuple(range(101)))


def test_phantoms_the_cache_lacks_are_refused_when_their_disk_does_not_fit(monkeypatch):
    from sonogym.anatomy.phantom import PhantomParams, cache_entry_bytes, is_cached, load_phantom

    load_phantom(0, PhantomParams(spacing=0.002))  # seed 0 is cached, 1..9 are not
    assert is_cached(0, PhantomParams(spacing=0.002))
    assert not is_cached(1, PhantomParams(spacing=0.002))
    per = cache_entry_bytes(0.002)
    assert per == pytest.approx(90e6 / 8)
    monkeypatch.setattr(footprint, "_free_disk", lambda folder: int(8 * per))
    with pytest.raises(ResourceLimitError) as e:
        footprint.check_phantom_cache(list(range(10)), 0.002)
    msg = str(e.value)
    assert "building 9 phantoms the cache lacks" in msg  # the cached one costs nothing
    assert "SONOGYM_CACHE" in msg and "disk under" in msg
    footprint.check_phantom_cache([0, 1, 2, 3, 4, 5], 0.002)  # six entries fit 0.8 x 8
