"""DAgger warm start: the policy's mean learns the expert, PPO continues, eval reads the run."""

from __future__ import annotations

import json

import gymnasium as gym
import pytest
import torch

from sonogym.agents.adapter import SkrlEnvAdapter
from sonogym.agents.checkpoint import load_policy
from sonogym.agents.dagger import DaggerConfig, SampleBuffer, make_expert
from sonogym.agents.train import train
from sonogym.envs.rollout import rollout

ENV = dict(phantom_spacing=0.002, episode_length=40)


def _run(out, obs_mode="state", dagger=None, steps=32, **kw):
    torch.set_num_threads(1)
    return train(
        "navigation", "ppo", envs=2, steps=steps, seed=0, out=out, patients=(0,),
        obs_downsample=4, env_kwargs=dict(ENV, obs_mode=obs_mode), dagger=dagger,
        progress=False, **kw,
    )  # fmt: skip


def _expert_states(n_steps=80, seed=7):
    """Flat observations and the level-counting expert's actions along its own episodes, on
    starts no warm start saw."""
    env = gym.make_vec("SonoGym/Navigation-v0", num_envs=4, patients=(0,), obs_mode="state", **ENV)
    adapter, expert = SkrlEnvAdapter(env, 4), make_expert("navigation", "level-counting", env)
    obs, labels = [], []
    for step in rollout(env, expert, n_steps, seed=seed):
        obs.append(adapter.flatten(step.obs))
        labels.append(step.action)
    return torch.cat(obs), torch.cat(labels)


def _mse(run, checkpoint, obs, labels):
    model, _ = load_policy(run, run / "checkpoints" / checkpoint)
    with torch.no_grad():
        mean = model.act({"observations": obs}, role="policy")[1]["mean_actions"]
    return float((mean - labels).pow(2).mean())


@pytest.fixture(scope="module")
def state_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("dagger")
    dagger = DaggerConfig("level-counting", 160, iterations=4, updates=100)
    warm = _run(root / "warm", dagger=dagger).out
    cold = _run(root / "cold").out
    return warm, cold


def test_the_warm_start_learns_the_expert_and_ppo_trains_on(state_runs):
    warm, cold = state_runs
    cfg = json.loads((warm / "config.json").read_text())
    assert cfg["dagger"] == {
        "expert": "level-counting", "steps": 160, "iterations": 4, "buffer": 16384,
        "updates": 100, "batch_size": 256, "learning_rate": 3e-4,
    }  # fmt: skip
    result = cfg["dagger_result"]
    assert result["beta"] == [1.0, 0.666667, 0.333333, 0.0]
    assert result["samples_seen"] == result["samples_kept"] == 160 * 2
    assert result["final_mse"] < 0.5 * result["mse_before"]
    # on fresh expert-visited states the warm-started policy acts far more like the expert
    obs, labels = _expert_states()
    warm_mse, cold_mse = (_mse(r, "agent_0.pt", obs, labels) for r in (warm, cold))
    print(f"fresh expert states: MSE warm {warm_mse:.3f}, untrained {cold_mse:.3f}; {result}")
    assert warm_mse < 0.5 * cold_mse
    # PPO continued from those weights; the warm start's seconds count in times.json
    first = torch.load(warm / "checkpoints" / "agent_0.pt", weights_only=True)["policy"]
    last = torch.load(warm / "checkpoints" / "agent_32.pt", weights_only=True)["policy"]
    assert any(not torch.equal(first[k], last[k]) for k in first)
    times = json.loads((warm / "checkpoints" / "times.json").read_text())
    assert times["32"]["cpu_s"] >= result["cpu_s"]


def test_sonogym_eval_evaluates_the_warm_started_run(state_runs):
    from typer.testing import CliRunner

    from sonogym.cli import app

    warm, _ = state_runs
    res = CliRunner().invoke(app, ["eval", "--run", str(warm), "--trials", "2", "--envs", "2"])
    assert res.exit_code == 0, res.output
    assert "position" in res.output


def test_a_resumed_run_keeps_its_warm_start_and_does_not_redo_it(state_runs, tmp_path):
    import shutil

    warm = shutil.copytree(state_runs[0], tmp_path / "warm")
    lines: list[str] = []
    _run(warm, steps=64, resume=True, log=lines.append)
    cfg = json.loads((warm / "config.json").read_text())
    assert cfg["dagger"]["expert"] == "level-counting" and "final_mse" in cfg["dagger_result"]
    assert not any(line.startswith("dagger round") for line in lines)
    with pytest.raises(ValueError, match="dagger define a new run"):
        _run(warm, steps=96, resume=True, dagger=DaggerConfig("expert", 8, iterations=2))


def test_an_image_warm_start_trains_the_conv_policy_from_8_bit_samples(tmp_path):
    dagger = DaggerConfig("level-counting", 8, iterations=2, updates=20)
    run = _run(tmp_path / "img", obs_mode="us_scan", dagger=dagger).out
    result = json.loads((run / "config.json").read_text())["dagger_result"]
    assert result["samples_kept"] == 16 and result["final_mse"] < result["mse_before"]
    first = torch.load(run / "checkpoints" / "agent_0.pt", weights_only=True)["policy"]
    assert "encoder.branches.image.0.weight" in first


def test_the_buffer_keeps_the_latest_samples_images_in_8_bits():
    env = gym.make_vec(
        "SonoGym/Navigation-v0", num_envs=2, patients=(0,), obs_mode="us_scan", **ENV
    )
    adapter = SkrlEnvAdapter(env, 4, {"motion": 100.0})
    layout = adapter.layout  # heading (6), image (3, 50, 37), motion (4)
    assert SampleBuffer.bytes_per_sample(adapter, 3) == 3 * 50 * 37 + 4 * (6 + 4) + 4 * 3
    buf = SampleBuffer(3, adapter, 3)
    obs, _ = env.reset(seed=0)
    flat = adapter.flatten_raw(obs)
    buf.add(flat, torch.ones(2, 3))
    buf.add(flat * 0.5, 2 * torch.ones(2, 3))  # wraps: the first sample is overwritten
    assert (buf.count, buf.seen) == (3, 4)
    got, actions = buf.get(torch.arange(3))
    assert actions[:, 0].tolist() == [2.0, 1.0, 2.0]
    image = slice(6, 6 + 3 * 50 * 37)
    want = torch.stack([flat[1] * 0.5, flat[1], flat[0] * 0.5])
    assert (got[:, image] - want[:, image]).abs().max() <= 0.5 / 255 + 1e-6
    assert torch.equal(got[:, : image.start], want[:, : image.start])
    assert torch.equal(got[:, image.stop :], want[:, image.stop :])
    assert layout.keys == ("heading", "image", "motion")


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        (dict(steps=0), "steps must be >= 1"),
        (dict(steps=4, iterations=8), "at least one step per round"),
        (dict(buffer=0), "buffer must be >= 1"),
        (dict(learning_rate=0.0), "learning_rate must be > 0"),
        (dict(updates=2.5), "must be an integer"),
    ],
)
def test_bad_settings_are_refused(kw, message):
    with pytest.raises(ValueError, match=message):
        DaggerConfig(**{"expert": "expert", "steps": 100, **kw})


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--dagger-steps", "100"], "--dagger-expert and --dagger-steps go together"),
        (["--dagger-expert", "level-counting"], "go together"),
        (["--dagger-expert", "levels", "--dagger-steps", "100"], "has no such expert"),
        (["--dagger-expert", "expert", "--dagger-steps", "0"], "must be a positive integer"),
    ],
)
def test_the_cli_refuses_bad_dagger_options(args, message, tmp_path):
    from typer.testing import CliRunner

    from sonogym.cli import app

    cmd = ["train", "--task", "navigation", "--out", str(tmp_path / "x"), *args]
    res = CliRunner().invoke(app, cmd)
    flat = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code != 0 and message in flat, res.output
    assert not (tmp_path / "x").exists()


def test_the_level_counting_expert_is_navigations_only(tmp_path):
    from typer.testing import CliRunner

    from sonogym.cli import app

    cmd = ["train", "--task", "surgery", "--out", str(tmp_path / "x")]
    res = CliRunner().invoke(
        app, [*cmd, "--dagger-expert", "level-counting", "--dagger-steps", "9"]
    )
    flat = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code != 0 and "choose from ['expert']" in flat, res.output
