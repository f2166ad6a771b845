"""The command line's shared run flags and renamed names: ``train`` and ``sweep`` take the
same ``RunOptions`` flags with the same help; the options renamed from ``--preset``
(``image --us-model``, ``record --recipe``, ``il-train --size``) refuse the old spelling; the
reference model's former simulator name ``sonogym`` is taken with a one-line note."""

from __future__ import annotations

import dataclasses

import pytest
from typer.main import get_command
from typer.testing import CliRunner

from sonogym.agents.options import RunOptions, flag
from sonogym.cli import _simulator_name, app


def _options(name: str) -> dict[str, tuple[str | None, object]]:
    command = get_command(app).commands[name]
    return {o: (p.help, p.default) for p in command.params for o in p.opts}


@pytest.mark.parametrize("name", ["train", "sweep"])
def test_train_and_sweep_take_every_run_option_with_its_one_help(name):
    opts = _options(name)
    for f in dataclasses.fields(RunOptions):
        assert opts[flag(f.name)] == (f.metadata["help"], None), f.name


def test_run_options_refuse_counts_below_one_and_unknown_presets_naming_the_flag():
    with pytest.raises(ValueError, match="--obs-downsample must be a positive integer, got 0"):
        RunOptions(obs_downsample=0).check()
    with pytest.raises(ValueError, match=r"unknown preset 'gpu'; choose from \['auto'"):
        RunOptions(preset="gpu").check()
    RunOptions(steps=1, envs=2, preset="cpu").check()


def test_run_options_env_kwargs_in_si_and_parsed():
    opts = RunOptions(phantom_spacing=2.0, learned_nets="0, 3,nets/g.pt", patients=["1-3", "7"],
                      simulator="learned", obs_mode="state")  # fmt: skip
    assert opts.env_kwargs() == {
        "phantom_spacing": 0.002,  # mm on the command line, m in the env
        "obs_mode": "state",
        "learned_nets": (0, 3, "nets/g.pt"),
        "simulator": "learned",
        "patients": (1, 2, 3, 7),
    }
    assert RunOptions().env_kwargs() == {} and RunOptions(envs=3).given() == ["--envs"]


def test_sweep_resume_names_every_run_option_it_refuses(tmp_path):
    args = ["--resume", "--obs-mode", "state", "--threads", "1"]
    res = CliRunner().invoke(app, ["sweep", "--task", "navigation", "--out", str(tmp_path), *args])
    if "needs Ray Tune" in str(res.exception):
        pytest.skip("Ray Tune is not installed")
    flat = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code != 0 and "leave out --obs-mode, --threads" in flat, res.output


def test_the_former_simulator_name_is_taken_and_said(capsys):
    assert _simulator_name("train", None) is None
    assert _simulator_name("train", "learned") == "learned"
    assert _simulator_name("train", "sonogym") == "reference"
    err = capsys.readouterr().err
    assert err.strip() == (
        "sonogym train: simulator 'sonogym' is now called 'reference'; "
        "the old name is removed in 0.3.0"
    )


@pytest.mark.parametrize(
    ("command", "old", "new"),
    [("image", "--preset", "--us-model"), ("record", "--preset", "--recipe"),
     ("il-train", "--preset", "--size")],
)  # fmt: skip
def test_renamed_options_refuse_the_old_spelling(command, old, new):
    params = {o: p for p in get_command(app).commands[command].params for o in p.opts}
    assert new in params and not params[new].hidden
    assert old not in params
    res = CliRunner().invoke(app, [command, old, "x"])
    assert res.exit_code != 0 and old in res.output
