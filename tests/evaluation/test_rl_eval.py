"""RL evaluation: a trained run's policy, the expert and a random policy on the same starts."""

from __future__ import annotations

import json

import pytest
import torch

from sonogym.agents.train import train
from sonogym.envs.identity import identity
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
    # what the episodes ran on and what the policy learned on, as the run recorded it
    made = identity("navigation", {"patients": (0,), "phantom_spacing": 0.002})
    assert saved["identity"] == made
    assert saved["train_identity"] == json.loads((nav_run / "config.json").read_text())["identity"]
    assert saved["train_identity"] == made
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
    # other test patients: a seed range, saved under the name given
    res = CliRunner().invoke(app, ["eval", "--run", str(nav_run), "--trials", "2", "--envs", "2",
                                   "--patients", "7-8", "--name", "pop"])  # fmt: skip
    assert res.exit_code == 0, res.output
    saved = json.loads((nav_run / "eval-pop.json").read_text())
    assert saved["env_overrides"]["patients"] == [7, 8] and saved["protocol"] == "pop"
    # the policy alone (choosing checkpoints need not re-run the expert and a random policy)
    res = CliRunner().invoke(app, ["eval", "--run", str(nav_run), "--trials", "2", "--envs", "2",
                                   "--controllers", "policy", "--name", "alone"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert set(json.loads((nav_run / "eval-alone.json").read_text())["results"]) == {"policy"}
    res = CliRunner().invoke(app, ["eval", "--run", str(nav_run), "--controllers", "oracle"])
    assert res.exit_code != 0 and "unknown controllers ['oracle']" in res.output
    res = CliRunner().invoke(app, ["eval", "--run", str(nav_run), "--patients", "8-7"])
    assert res.exit_code != 0 and "8 > 7" in res.output
    res = CliRunner().invoke(app, ["eval", "--run", str(nav_run), "--patients", "7",
                                   "--protocol", "odt-patient"])  # fmt: skip
    assert res.exit_code != 0 and "cannot be combined" in res.output
    with pytest.raises(ValueError, match="letters, digits"):
        evaluate_run(nav_run, name="../elsewhere")  # a log name is a file name, not a path
    with pytest.raises(FileNotFoundError, match="config.json"):
        evaluate_run(tmp_path)
    with pytest.raises(ValueError, match="unknown controllers"):
        evaluate_run(nav_run, controllers=("oracle",))


def test_protocol_eval_saves_episode_logs_and_refuses_held_out_runs(nav_run, tmp_path):
    import shutil

    import numpy as np

    from sonogym.evaluation.episodes import load_log, log_path
    from sonogym.evaluation.protocols import ProtocolError
    from sonogym.evaluation.report import build_report

    res = evaluate_run(nav_run, trials=2, envs=2, protocol="odt-patient", plot=False)
    log = load_log(log_path(nav_run, "odt-patient"))
    assert log.meta["test_env"]["patients"] == [5] and log.meta["train_env"]["patients"] == [0]
    assert log.meta["test_env"]["imaging_randomization"] is False  # what the test ran with
    assert log.meta["protocol"] == "odt-patient" and log.meta["trials"] == 2
    assert log.meta["num_envs"] == 2  # which env, so which patient, ran each episode
    assert json.loads((nav_run / "eval-odt-patient.json").read_text())["protocol"] == "odt-patient"
    for c in ("policy", "expert", "random"):
        m, tr = log.metrics[c], log.tracks[c]
        assert tr.shape == (2, 11, 3)  # start + 10 steps; x, z (mm), yaw (deg) from the goal
        # the logged path ends where the episode's metrics were measured
        np.testing.assert_allclose(np.hypot(tr[:, -1, 0], tr[:, -1, 1]), m["position_error_mm"],
                                   atol=1e-3)  # fmt: skip
        np.testing.assert_allclose(np.abs(tr[:, -1, 2]), m["angle_error_deg"], atol=1e-3)
        assert float(m["return"].mean()) == pytest.approx(res[c]["return"][0], rel=1e-6)

    # a run trained on the held-out patient is refused before anything runs
    leaked = tmp_path / "leaked"
    shutil.copytree(nav_run, leaked)
    cfg = json.loads((leaked / "config.json").read_text())
    cfg["task_config"]["env_kwargs"]["patients"] = [0, 5]
    (leaked / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ProtocolError, match="held-out"):
        evaluate_run(leaked, trials=2, envs=2, protocol="odt-patient")
    with pytest.raises(ProtocolError, match="learned simulator"):
        evaluate_run(nav_run, trials=2, envs=2, protocol="odt-sim")
    with pytest.raises(ValueError, match="contradict"):
        evaluate_run(nav_run, trials=2, protocol="odt-patient", env_overrides={"patients": (1,)})

    # the report reads these logs only: twice, the same numbers
    a = build_report("navigation", [nav_run], tmp_path / "a", curves=False)
    b = build_report("navigation", [nav_run], tmp_path / "b", curves=False)
    assert (a.parent / "metrics.csv").read_text() == (b.parent / "metrics.csv").read_text()
    assert (a.parent / "bars.png").exists() and "(seed 0)" in a.read_text()


def test_tables_give_the_median_and_the_share_within_a_metrics_tolerance():
    import numpy as np

    from sonogym.evaluation.rl_eval import distribution, format_table

    errors = {
        "position_error_mm": np.array([1.0, 5.0, 10.0, 12.0, 30.0]),
        "angle_error_deg": np.array([1.0, 2.0, 3.0, 4.0, 90.0]),
    }
    d = distribution("navigation", errors)
    assert d["position_error_mm"] == {"median": 10.0, "within": 0.6, "tolerance": 10.0}
    assert d["angle_error_deg"] == {"median": 3.0}  # no tolerance declared
    table = format_table({"policy": {"position_error_mm": (11.6, 10.6)}}, {"policy": d})
    assert "11.600 ± 10.600 (median 10.000; 60 % within 10)" in table
