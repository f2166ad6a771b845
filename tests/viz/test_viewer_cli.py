"""``sonogym view`` on the command line: without the viewer extra it says how to get it; with
it, bad combinations of options are named before anything runs, and a view is written."""

from __future__ import annotations

import sys

import pytest
import torch
from typer.testing import CliRunner

from sonogym.cli import app


def flat(output: str) -> str:
    """The output as one line of words (error boxes wrap long messages)."""
    return " ".join(output.replace("│", " ").split())


def test_without_rerun_the_view_says_how_to_install_it(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError
    res = CliRunner().invoke(
        app, ["view", "--task", "navigation", "--save", str(tmp_path / "v.rrd")]
    )
    assert res.exit_code == 1
    assert "pip install 'sonogym[viewer]'" in res.output and "make install" in res.output
    assert not (tmp_path / "v.rrd").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        ([], "give --task, --policy RUN or --pretrained NAME"),
        (["--run", "r", "--task", "navigation"], "--task step an env"),
        (["--dataset", "d", "--steps", "3"], "--steps step an env"),
        (["--run", "r", "--dataset", "d"], "--run or --dataset, not both"),
        (["--task", "navigation", "--web", "--save", "x.rrd"], "not both"),
        (["--task", "navigation", "--seed", "1", "--patient", "p"], "--patient or --seed"),
        (["--task", "navigation", "--policy", "nowhere"], "neither expert nor random"),
        (["--task", "navigation", "--pretrained", "nope"], "no pretrained policy 'nope'"),
        (["--task", "navigation", "--env-option", "nope=1"], "navigation has no such option"),
        (["--task", "navigation", "--save", "x.txt"], "an .rrd file"),
        (["--task", "navigation", "--steps", "0"], "--steps must be a positive integer"),
    ],
)
def test_bad_options_are_named(args, message, tmp_path, monkeypatch):
    pytest.importorskip("rerun", reason="the viewer needs rerun-sdk: pip install 'sonogym[viewer]'")
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["view", *args])
    assert res.exit_code != 0
    assert message in flat(res.output), res.output
    assert not (tmp_path / "runs").exists()  # refused before anything was written


def test_view_a_trained_run_policy_from_the_command_line(tmp_path):
    pytest.importorskip("rerun", reason="the viewer needs rerun-sdk: pip install 'sonogym[viewer]'")
    from sonogym.agents.train import train

    torch.set_num_threads(1)
    run = tmp_path / "nav"
    train("navigation", "ppo", envs=2, steps=8, out=run, patients=(0,), obs_downsample=2,
          env_kwargs=dict(phantom_spacing=0.002, episode_length=5), progress=False)  # fmt: skip
    out = tmp_path / "v.rrd"
    # the run's task and training env (2 mm phantom, 5-step episodes): by default the episode
    # up to its last state (4 steps), here one step more, into the next episode
    res = CliRunner().invoke(app, ["view", "--policy", str(run), "--save", str(out)])
    assert res.exit_code == 0, res.output
    assert f"wrote {out}" in res.output and "step 0..4" in res.output
    assert f"rerun {out}" in res.output and "after step 4: position_error_mm" in res.output
    res = CliRunner().invoke(app, ["view", "--policy", str(run), "--steps", "6", "--save",
                                   str(out)])  # fmt: skip
    assert res.exit_code == 0 and "episode 0 ended: position_error_mm" in res.output
    res = CliRunner().invoke(app, ["view", "--policy", str(run), "--task", "surgery"])
    assert res.exit_code != 0 and "is a navigation run, not surgery" in flat(res.output)
