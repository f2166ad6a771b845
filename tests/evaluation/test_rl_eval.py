"""RL evaluation: a trained run's policy, the expert and a random policy on the same starts."""

from __future__ import annotations

import json

import pytest
import torch

from sonogym.agents.train import train
from sonogym.evaluation.rl_eval import evaluate_run


@pytest.fixture(scope="module")
def nav_run(tmp_path_factory):
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("rl") / "nav"
    train(
        "navigation",
        "ppo",
        envs=2,
        steps=32,
        out=out,
        patients=(0,),
        obs_downsample=2,
        env_kwargs=dict(phantom_spacing=0.002, episode_length=10),
        progress=False,
    )
    return out


def test_eval_table_for_policy_expert_random(nav_run):
    res = evaluate_run(nav_run, trials=3, envs=2)
    assert set(res) == {"policy", "expert", "random"}
    for r in res.values():
        assert set(r) >= {"position_error_mm", "angle_error_deg", "return"}
    # 10 expert steps from a 130 x 130 mm start square close the gap better than random ones
    assert res["expert"]["return"][0] > res["random"]["return"][0]
    saved = json.loads((nav_run / "eval.json").read_text())
    assert saved["trials"] == 3 and saved["task"] == "navigation"
    md = (nav_run / "eval.md").read_text()
    assert md.count("\n") == 5 and "| expert |" in md
    # same seed, same starts: the deterministic policy's metrics repeat
    again = evaluate_run(nav_run, trials=3, envs=2, controllers=("policy",))
    assert again["policy"] == res["policy"]


def test_eval_cli_and_errors(nav_run, tmp_path):
    from typer.testing import CliRunner

    from sonogym.cli import app

    res = CliRunner().invoke(app, ["eval", "--run", str(nav_run), "--trials", "2", "--envs", "2"])
    assert res.exit_code == 0, res.output
    assert "| policy |" in res.output and "position_error_mm" in res.output
    with pytest.raises(FileNotFoundError, match="config.json"):
        evaluate_run(tmp_path)
    with pytest.raises(ValueError, match="unknown controllers"):
        evaluate_run(nav_run, controllers=("oracle",))
