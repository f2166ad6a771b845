"""The policy mean's bound penalty: a mean the env would clip is pulled back into the box."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.configs import task_config
from sonogym.agents.networks import SharedActorCritic

LAYOUT = ObsLayout(("_",), ((6,),))
BOX = gym.spaces.Box(np.array([-0.3, -0.3, -0.3, -0.1, -0.1, -0.1], np.float32),
                     np.array([0.3, 0.3, 0.3, 0.1, 0.1, 0.1], np.float32))  # fmt: skip


def _policy(penalty: float, bias: list[float]) -> SharedActorCritic:
    torch.manual_seed(0)
    model = SharedActorCritic("surgery", LAYOUT, BOX, "cpu", "paper", -3.0, 1.0, penalty)
    with torch.no_grad():
        model.mean_head.weight.zero_()
        model.mean_head.bias.copy_(torch.tensor(bias))
    return model


def _bias_grad(model: SharedActorCritic, n: int = 8) -> torch.Tensor:
    obs = torch.randn(n, 6)
    _, out = model.act({"observations": obs, "taken_actions": torch.zeros(n, 6)}, role="policy")
    (0.0 * out["mean_actions"].sum()).backward()  # a loss with no gradient of its own
    return model.mean_head.bias.grad


def test_penalty_gradient_is_the_squared_excess_outside_the_box_only():
    bias = [0.5, 0.0, -0.1, 1.05, -0.3, 0.05]  # excess 0.2, 0, 0, 0.95, -0.2, 0
    grad = _bias_grad(_policy(10.0, bias))
    # d/d(mean) of 10 * mean_over_batch(sum excess^2) summed over the batch = 2 * 10 * excess
    expected = 2 * 10.0 * torch.tensor([0.2, 0.0, 0.0, 0.95, -0.2, 0.0])
    torch.testing.assert_close(grad, expected, rtol=1e-5, atol=1e-6)
    assert torch.equal(_bias_grad(_policy(0.0, bias)), torch.zeros(6))  # off: no gradient


def test_mean_outside_the_box_is_pulled_back_in_by_gradient_steps():
    model = _policy(10.0, [0.0, 0.0, 0.0, 1.0, -1.0, 0.0])
    opt = torch.optim.SGD([model.mean_head.bias], lr=0.02)
    for _ in range(200):
        opt.zero_grad()
        _bias_grad(model)
        opt.step()
    b = model.mean_head.bias.detach()
    assert b[3] <= 0.1 + 1e-3 and b[4] >= -0.1 - 1e-3  # back at the box's edge
    assert torch.equal(b[:3], torch.zeros(3))  # inside the box: untouched


def test_penalty_is_a_task_setting_off_by_default_and_validated():
    assert task_config("surgery").mean_bound_penalty == 0.0
    assert task_config("surgery", mean_bound_penalty=10.0).mean_bound_penalty == 10.0
    with pytest.raises(ValueError, match="mean_bound_penalty must be >= 0"):
        SharedActorCritic("surgery", LAYOUT, BOX, "cpu", "paper", 0.0, 1.0, -1.0)
