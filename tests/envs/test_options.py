"""Env options written as text: one parser per kind, ValueError naming the item."""

import pytest

from sonogym.envs.options import (
    parse_env_options,
    parse_learned_nets,
    parse_patients,
    parse_value,
)


def test_values_read_as_numbers_flags_or_words():
    assert [parse_value(v) for v in ("3", "2.5", " true", "None", "us")] == [
        3, 2.5, True, None, "us",
    ]  # fmt: skip


def test_patients_and_learned_nets():
    assert parse_patients(None) is None and parse_patients([]) is None
    assert parse_patients(["2-4", "9", "subject"]) == (2, 3, 4, 9, "subject")
    with pytest.raises(ValueError, match="patient range '5-3': 5 > 3; write it low-high"):
        parse_patients(["5-3"])
    assert parse_learned_nets("0,1, runs/a/generator.pt") == (0, 1, "runs/a/generator.pt")


def test_env_options_name_what_is_wrong():
    assert parse_env_options("navigation", ["w1=0.05", "episode_length=20.0"]) == {
        "w1": 0.05,
        "episode_length": 20,
    }
    with pytest.raises(ValueError, match="use --obs-mode for this option"):
        parse_env_options("navigation", ["obs_mode=state"], {"obs_mode": "--obs-mode"})
    with pytest.raises(ValueError, match="navigation has no such option"):
        parse_env_options("navigation", ["w9=1"])
    with pytest.raises(ValueError, match="--env-option w1 is given twice"):
        parse_env_options("navigation", ["w1=1", "w1=2"])


def test_env_options_are_checked_together_with_the_flags_values():
    """A check across options sees the run's values: ``observe_tilt`` needs a Dict
    observation, which ``--obs-mode`` (``flag_values``) or another option may give; refused
    without one, naming the option as typed."""
    tilt = ["observe_tilt=true"]
    with pytest.raises(ValueError, match=r"--env-option observe_tilt=true: .*obs_mode 'us'"):
        parse_env_options("navigation", tilt)
    assert parse_env_options("navigation", tilt, flag_values={"obs_mode": "us_scan"}) == {
        "observe_tilt": True
    }
    both = parse_env_options("navigation", ["obs_mode=us_memory", *tilt])
    assert both == {"obs_mode": "us_memory", "observe_tilt": True}
    with pytest.raises(ValueError, match=r"--env-option w1=nan: "):  # not blamed on the tilt
        parse_env_options("navigation", ["obs_mode=us_memory", *tilt, "w1=nan"])
