"""The policy mean and the action box: a mean the env would clip is kept in the box by
construction (``bounded_mean``, surgery's default) or pulled back in by a penalty."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch

from sonogym.agents.adapter import ObsLayout
from sonogym.agents.configs import task_config
from sonogym.agents.networks import SharedActorCritic, squash_into_box

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
    assert task_config("surgery").learning.mean_bound_penalty == 0.0
    rl = task_config("surgery")
    learning = dataclasses.replace(rl.learning, mean_bound_penalty=10.0)
    assert task_config("surgery", learning=learning).learning.mean_bound_penalty == 10.0
    with pytest.raises(ValueError, match="mean_bound_penalty must be >= 0"):
        SharedActorCritic("surgery", LAYOUT, BOX, "cpu", "paper", 0.0, 1.0, -1.0)


def test_bounded_mean_stays_in_the_box_and_starts_as_the_raw_mean():
    low, high = torch.tensor(BOX.low), torch.tensor(BOX.high)
    raw = torch.tensor([[5.0, -5.0, 0.0, 1.05, -0.3, 0.05], [1e-3, -1e-3, 2e-3, 1e-4, 0, -1e-4]])
    m = squash_into_box(raw, low, high)
    assert bool((m <= high).all() and (m >= low).all())
    # far beyond the box: at its edge (tanh(5 / 0.3) rounds to 1 in float32), never across it
    torch.testing.assert_close(m[0, :2], torch.tensor([0.3, -0.3]))
    assert m[0, 3] == pytest.approx(0.1 * np.tanh(10.5)) and m[0, 2] == 0.0
    # near the centre the same as unsquashed (the small initial head acts as before)
    torch.testing.assert_close(m[1], raw[1], rtol=1e-4, atol=1e-9)
    # an asymmetric box: the centre maps to itself, the mean stays inside
    lo, hi = torch.tensor([0.0, -2.0]), torch.tensor([1.0, 0.0])
    out = squash_into_box(torch.tensor([[0.5, -1.0], [9.0, -9.0]]), lo, hi)
    torch.testing.assert_close(out[0], torch.tensor([0.5, -1.0]))
    assert bool((out[1] <= hi).all() and (out[1] >= lo).all())


def test_bounded_mean_is_surgerys_default_and_what_its_policy_acts_with():
    assert task_config("surgery").learning.bounded_mean is True
    assert task_config("navigation").learning.bounded_mean is False
    torch.manual_seed(0)
    model = SharedActorCritic("surgery", LAYOUT, BOX, "cpu", "paper", -3.0, 1.0,
                              bounded_mean=True)  # fmt: skip
    obs = 100 * torch.randn(64, 6)  # far outside what training saw: raw means of order 10
    mean = model.act({"observations": obs}, role="policy")[1]["mean_actions"]
    assert bool((mean.abs() <= torch.tensor(BOX.high)).all())
    # a raw mean 1.5 half-widths beyond the centre still passes gradient (tanh' = 0.18), where
    # the env's clip passes none
    with torch.no_grad():
        model.mean_head.weight.zero_()
        model.mean_head.bias.copy_(torch.tensor([0.45, -0.45, 0.0, 0.15, -0.15, 0.0]))
    mean = model.act({"observations": obs}, role="policy")[1]["mean_actions"]
    mean.sum().backward()
    grad = model.mean_head.bias.grad / 64
    torch.testing.assert_close(grad, 1 - torch.tanh(torch.tensor([1.5, 1.5, 0, 1.5, 1.5, 0])) ** 2)
