"""PPO-Lagrangian: PID multiplier, cost value learning, a tiny surgery run."""

from __future__ import annotations

import torch

from sonogym.agents.algorithms.ppo_lag.agent import PIDLagrangian
from sonogym.agents.train import train


def test_pid_multiplier():
    pid = PIDLagrangian(0.05, 0.0005, 0.1)
    assert pid.update(2.0, 5.0) == 0.0  # below the limit: no penalty
    assert float(pid.integral) == 0.0  # the integral does not wind below 0
    lam = pid.update(9.0, 5.0)  # e = 4, I = 4, rise = 7
    assert abs(lam - (0.05 * 4 + 0.0005 * 4 + 0.1 * 7)) < 1e-6
    lam2 = pid.update(9.0, 5.0)  # e = 4, I = 8, no rise
    assert abs(lam2 - (0.05 * 4 + 0.0005 * 8)) < 1e-6
    assert set(pid.state_dict()) == {"integral", "previous", "value", "started"}


def test_ppo_lag_tiny_surgery_run(tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "lag"
    res = train(
        "surgery",
        "ppo-lag",
        envs=2,
        steps=32,
        out=run,
        patients=(0,),
        env_kwargs=dict(phantom_spacing=0.002, episode_length=10, require_free_start=False),
        progress=False,
    )
    first = torch.load(run / "checkpoints" / "agent_0.pt", weights_only=False)
    last = torch.load(res.checkpoint, weights_only=False)
    assert {"cost_value", "lagrangian", "cost_optimizer"} <= set(last)
    for name in ("policy", "cost_value"):
        moved = [k for k in first[name] if not torch.equal(first[name][k], last[name][k])]
        assert any(k.startswith("encoder.") for k in moved), name
    assert float(last["lagrangian"]["value"]) >= 0.0
