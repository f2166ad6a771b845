"""PPO + safety filter: the cost critic learns from info["cost"] and filters at test time."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.checkpoint import load_cost_critic
from sonogym.agents.safety_filter import CostCritic, filter_actions
from sonogym.agents.train import train
from sonogym.envs.registry import make_vec
from sonogym.evaluation.rl_eval import controller_policy, evaluate_run
from sonogym.evaluation.trained import load_run

LAYOUT = ObsLayout(("image", "pose"), ((5, 50, 37), (7,)))
BOX = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)


def test_filter_zeroes_actions_above_threshold():
    critic = CostCritic("surgery", LAYOUT, BOX)
    obs, act = torch.rand(4, LAYOUT.size), torch.rand(4, 6)
    q, _ = critic.act({"observations": obs, "taken_actions": act}, role="cost_critic")
    assert q.shape == (4, 1)
    thr = float(q.detach().median())
    out, unsafe = filter_actions(critic, obs, act, thr)
    assert torch.equal(unsafe, q.view(-1) > thr) and unsafe.any() and (~unsafe).any()
    assert torch.equal(out[unsafe], torch.zeros_like(out[unsafe]))
    assert torch.equal(out[~unsafe], act[~unsafe])


def test_ppo_sf_trains_cost_critic_and_eval_filters(tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "sf"
    res = train(
        "surgery",
        "ppo-sf",
        envs=2,
        steps=32,
        out=run,
        patients=(0,),
        env_kwargs=dict(phantom_spacing=0.002, episode_length=10),
        progress=False,
    )
    first = torch.load(run / "checkpoints" / "agent_0.pt", weights_only=False)
    last = torch.load(res.checkpoint, weights_only=False)
    assert "cost_critic" in last and "cost_optimizer" in last
    moved = [
        k
        for k in first["cost_critic"]
        if not torch.equal(first["cost_critic"][k], last["cost_critic"][k])
    ]
    assert any(k.startswith("encoder.") for k in moved) and "head.1.weight" in moved
    critic, thr = load_cost_critic(run)
    assert thr == 0.5
    res = evaluate_run(run, trials=2, envs=2, controllers=("policy",))
    assert "safe_ratio" in res["policy"]
    # by default a ppo-sf run is evaluated with and without its filter, from the same starts
    res = evaluate_run(run, trials=2, envs=2, plot=False)
    assert list(res) == ["policy", "unfiltered", "expert", "random"]
    env = make_vec("surgery", 2, patients=(0,), phantom_spacing=0.002, episode_length=10)
    pol = controller_policy("policy", env, load_run(run), 0)
    raw = controller_policy("unfiltered", env, load_run(run), 0)
    assert pol.critic is not None and raw.critic is None
    obs, info = env.reset(seed=0)
    x = pol.adapter.flatten(obs)
    mean = pol.model.act({"observations": x}, role="policy")[1]["mean_actions"]
    assert torch.equal(raw.act(obs, info), mean)  # the unfiltered policy is the PPO mean
