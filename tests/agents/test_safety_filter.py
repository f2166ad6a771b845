"""PPO + safety filter: the cost critic learns from info["cost"] and filters at test time."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest
import torch

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.algorithms.ppo_sf.agent import (
    CostCritic,
    candidate_actions,
    filter_actions,
    load_cost_critic,
)
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
    out, unsafe = filter_actions(critic, obs, act, thr, mode="zero")
    assert torch.equal(unsafe, q.view(-1) > thr) and unsafe.any() and (~unsafe).any()
    assert torch.equal(out[unsafe], torch.zeros_like(out[unsafe]))
    assert torch.equal(out[~unsafe], act[~unsafe])


class AxisCritic:
    """A stand-in cost critic with a known answer: moving along +z (component 2) by more than
    0.01 costs 1; observations whose first entry is > 0.5 are "already unsafe" (every action
    costs 1)."""

    action_space = gym.spaces.Box(-0.3, 0.3, (6,), np.float32)

    def q_values(self, obs, actions):  # (K, N, A) -> (K, N)
        q = (actions[..., 2] > 0.01).float()
        return torch.where(obs[:, 0] > 0.5, torch.ones_like(q), q)


def test_candidates_are_variations_of_the_policy_action_inside_the_box():
    a = torch.tensor([[0.2, -0.1, 0.25, 0.05, 0.0, -0.08]])
    box = AxisCritic.action_space
    c = candidate_actions(a, torch.tensor(box.low), torch.tensor(box.high))
    assert c.shape == (2 * 6 + 4, 1, 6)
    assert torch.equal(c[0], a)  # the policy's action comes first
    assert torch.allclose(c[1], a / 2) and torch.allclose(c[2], a / 4)
    for i in range(6):
        zeroed, negated = a.clone(), a.clone()
        zeroed[0, i], negated[0, i] = 0.0, -a[0, i]
        assert torch.equal(c[3 + i], zeroed) and torch.equal(c[9 + i], negated)
    assert torch.equal(c[-1], torch.zeros_like(a))
    big = candidate_actions(torch.full((1, 6), 5.0), torch.tensor(box.low), torch.tensor(box.high))
    assert big.abs().max() <= 0.3  # clipped to the box


def test_search_filter_takes_the_nearest_action_predicted_safe():
    critic = AxisCritic()
    obs = torch.tensor([[0.0], [0.0], [1.0]])  # two safe states, one already unsafe
    act = torch.tensor(
        [
            [0.1, 0.0, 0.2, 0.0, 0.0, 0.0],
            [0.1, 0.0, -0.2, 0.0, 0.0, 0.0],
            [0.1, 0.0, 0.2, 0.0, 0.0, 0.0],
        ]
    )
    out, changed = filter_actions(critic, obs, act, 0.5, mode="search")
    # row 0: +z costs 1; halving or quartering still moves > 0.01 along z; the nearest safe
    # variation is the lateral move with z zeroed (negating z is twice as far)
    assert torch.equal(out[0], torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))
    assert torch.equal(out[1], act[1])  # predicted safe: untouched
    assert torch.equal(out[2], act[2])  # nothing predicted safe: the policy's action stays
    assert changed.tolist() == [True, False, False]
    zero, _ = filter_actions(critic, obs, act, 0.5, mode="zero")
    assert torch.equal(zero[0], torch.zeros(6)) and torch.equal(zero[2], torch.zeros(6))
    with pytest.raises(ValueError, match="unknown safety filter mode 'stop'"):
        filter_actions(critic, obs, act, 0.5, mode="stop")


def test_search_filter_leaves_the_policy_in_charge_outside_the_safe_set():
    """A critic that wrongly rates "no motion" safe for a tip already outside the safe set held
    such a drill still for the rest of its episode (IDT episode 74 of the image run, 5 % safe):
    where info["safe"] is False the search filter keeps the policy's action."""

    class StallingCritic(AxisCritic):
        def q_values(self, obs, actions):  # only no motion is predicted safe, everywhere
            return (actions.abs().sum(-1) > 0).float()

    obs = torch.zeros(3, 1)
    act = torch.tensor([[0.1, 0.0, 0.2, 0.0, 0.0, 0.05]]).repeat(3, 1)
    in_safe_set = torch.tensor([True, False, True])
    out, changed = filter_actions(StallingCritic(), obs, act, 0.5, "search", in_safe_set)
    assert torch.equal(out[0], torch.zeros(6)) and torch.equal(out[2], torch.zeros(6))
    assert torch.equal(out[1], act[1])  # outside the safe set: the policy's way back
    assert changed.tolist() == [True, False, True]
    # without the env's safety flag the critic alone decides (the stall this guards against)
    alone, _ = filter_actions(StallingCritic(), obs, act, 0.5, "search")
    assert torch.equal(alone, torch.zeros(3, 6))
    # the paper's zero rule is kept as published: it zeroes wherever Q_c says so
    zero, _ = filter_actions(StallingCritic(), obs, act, 0.5, "zero", in_safe_set)
    assert torch.equal(zero, torch.zeros(3, 6))


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
    critic, thr, mode = load_cost_critic(run)
    assert (thr, mode) == (0.5, "search")
    res = evaluate_run(run, trials=2, envs=2, controllers=("policy",))
    assert "safe_ratio" in res["policy"]
    # by default a ppo-sf run is evaluated with and without its filter, from the same starts
    res = evaluate_run(run, trials=2, envs=2, plot=False)
    assert list(res) == ["policy", "unfiltered", "expert", "random"]
    env = make_vec("surgery", 2, patients=(0,), phantom_spacing=0.002, episode_length=10)
    pol = controller_policy("policy", env, load_run(run), 0)
    raw = controller_policy("unfiltered", env, load_run(run), 0)
    assert pol.critic is not None and not hasattr(raw, "critic")
    obs, info = env.reset(seed=0)
    x = pol.adapter.flatten(obs)
    mean = pol.model.act({"observations": x}, role="policy")[1]["mean_actions"]
    assert torch.equal(raw.act(obs, info), mean)  # the unfiltered policy is the PPO mean
    # the env's safety flag reaches the filter: with a threshold that rejects the mean action
    # but keeps a variation of it, the filter changes it inside the safe set only
    box = pol.critic.action_space
    cands = candidate_actions(mean, torch.tensor(box.low), torch.tensor(box.high))
    q = pol.critic.q_values(x, cands).detach()
    pol.threshold = float(q[1:].min(0).values.max())
    assert (q[0] > pol.threshold).any()
    inside = {**info, "safe": torch.ones_like(info["safe"])}
    outside = {**info, "safe": torch.zeros_like(info["safe"])}
    assert not torch.equal(pol.act(obs, inside), mean)
    assert torch.equal(pol.act(obs, outside), mean)

    # the filter acts at test time only: eval can test the same run with other settings
    res = evaluate_run(run, trials=2, envs=2, controllers=("policy",), plot=False,
                       safety_filter={"mode": "zero", "threshold": 0.3})  # fmt: skip
    saved = json.loads((run / "eval.json").read_text())
    assert saved["safety_filter"] == {"mode": "zero", "threshold": 0.3}
    pol = controller_policy("policy", env, load_run(run), 0, safety_filter={"threshold": 0.2})
    assert (pol.filter_mode, pol.threshold) == ("search", 0.2)
    with pytest.raises(ValueError, match=r"threshold must be in \[0, 1\]"):
        evaluate_run(run, trials=2, envs=2, safety_filter={"threshold": 1.5})
    with pytest.raises(ValueError, match="unknown safety filter mode"):
        evaluate_run(run, trials=2, envs=2, safety_filter={"mode": "halt"})
