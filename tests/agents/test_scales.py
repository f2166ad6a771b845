"""Exploration and input scales per task: surgery's initial sigma fits its corridor, vector
observations are standardised by running statistics that checkpoints keep."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from sonogym.agents.adapter import RunningStandardizer, SkrlEnvAdapter
from sonogym.agents.algorithms import algo_config
from sonogym.agents.checkpoint import read_checkpoint, rl_policy
from sonogym.agents.configs import task_config
from sonogym.agents.networks import make_models
from sonogym.agents.train import train
from sonogym.envs.registry import make_vec


def with_learning(rl, **changes):
    """``rl`` (a TaskRLConfig) with ``changes`` to its learning settings."""
    return dataclasses.replace(rl, learning=dataclasses.replace(rl.learning, **changes))


def test_surgery_explores_at_the_corridors_scale():
    cfg = task_config("surgery")
    # ~5 mm / 0.05 rad per command, not sigma = 1
    assert math.exp(cfg.learning.init_log_std) == pytest.approx(0.05)
    env = make_vec("surgery", 1, obs_mode="state", phantom_spacing=0.002)
    adapter = SkrlEnvAdapter(env)
    model = make_models("surgery", adapter.layout, adapter.action_space, "cpu", "small",
                        cfg.learning.init_log_std)["policy"]  # fmt: skip
    assert torch.allclose(model.log_std.exp(), torch.full((6,), 0.05))
    # navigation and reconstruction keep the sigma = 1 that their CPU runs learned with
    assert task_config("navigation").learning.init_log_std == 0
    assert task_config("reconstruction").learning.init_log_std == 0


def test_running_standardizer_matches_the_pooled_statistics():
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 0.01, (n, 4)) for n in (5, 17, 1, 40)]
    s = RunningStandardizer(4)
    x0 = torch.tensor(batches[0])
    assert torch.allclose(s(x0), x0, rtol=1e-7)  # no update yet: the identity
    for b in batches:
        s(torch.tensor(b), update=True)
    pooled = np.concatenate(batches)
    np.testing.assert_allclose(s.mean.numpy(), pooled.mean(0), rtol=1e-12)
    np.testing.assert_allclose(s.var.numpy(), pooled.var(0), rtol=1e-9)
    z = s(torch.tensor(pooled)).numpy()
    np.testing.assert_allclose(z.mean(0), 0, atol=1e-9)
    np.testing.assert_allclose(z.std(0), 1, atol=1e-4)  # eps 1e-8 against var 1e-4


def test_surgery_state_inputs_reach_the_network_at_order_one(tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "sur"
    train("surgery", "ppo", envs=4, steps=32, out=run, patients=(0,), progress=False,
          env_kwargs=dict(phantom_spacing=0.002, obs_mode="state", episode_length=16))  # fmt: skip
    ck = read_checkpoint(run / "checkpoints" / "agent_32.pt")
    stats = ck["obs_standardizer"]
    assert stats["count"] == 32 * 4 + 4  # every rollout observation, the first reset's too
    env = make_vec("surgery", 8, obs_mode="state", phantom_spacing=0.002)
    obs, _ = env.reset(seed=5)
    raw = obs[:, :3]
    assert raw.abs().max() < 0.3  # metres: millimetre differences are 1e-3 at the network
    policy = rl_policy(run, env)
    z = policy.adapter.flatten(obs)
    assert 0.3 < float(z[:, :3].abs().mean()) < 5.0  # standardised with the run's statistics
    assert policy.adapter.update_stats is False  # evaluation does not move the statistics
    policy.act(obs, {})
    assert policy.adapter.standardizer.count.item() == stats["count"].item()
    # the run records which state it learned from; one trained on the old state (pose in {G},
    # version 1, or no version recorded) is refused by eval and by resume, not misread
    cfg_path = run / "config.json"
    cfg = json.loads(cfg_path.read_text())
    assert cfg["obs_version"] == 2
    del cfg["obs_version"]
    cfg_path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="version 1 of the surgery observation 'state'.*emits "
                                         "version 2"):  # fmt: skip
        rl_policy(run, env)
    with pytest.raises(ValueError, match="Retrain the run"):
        train("surgery", "ppo", steps=64, out=run, resume=True, progress=False)


def test_surgery_exploration_narrows_geometrically_to_its_floor():
    from sonogym.agents.networks import log_std_ceiling

    cfg = task_config("surgery").learning
    assert math.exp(cfg.final_log_std) == pytest.approx(0.005) and cfg.anneal_steps == 100_000
    a, b, n = cfg.init_log_std, cfg.final_log_std, cfg.anneal_steps
    assert log_std_ceiling(0, a, b, n) == pytest.approx(a)
    # halfway in log space: the geometric mean of 0.05 and 0.005
    assert math.exp(log_std_ceiling(n // 2, a, b, n)) == pytest.approx(math.sqrt(0.05 * 0.005))
    assert log_std_ceiling(n, a, b, n) == log_std_ceiling(5 * n, a, b, n) == pytest.approx(b)
    steps = [log_std_ceiling(t, a, b, n) for t in range(0, n + 1, 997)]
    assert all(x > y for x, y in zip(steps, steps[1:], strict=False))
    # the other tasks keep a free sigma
    assert task_config("navigation").learning.final_log_std is None


def test_training_samples_under_the_ceiling_and_eval_restores_it(tmp_path):
    import dataclasses

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from sonogym.agents.checkpoint import load_policy
    from sonogym.agents.configs import resolve_train_config
    from sonogym.agents.train import run_training

    torch.set_num_threads(1)
    base = resolve_train_config(
        "surgery", "ppo", preset="cpu", envs=4, steps=64, checkpoint_interval=32,
        env_kwargs=dict(patients=(0,), phantom_spacing=0.002, obs_mode="state",
                        episode_length=16),
    )  # fmt: skip
    init, final = math.log(0.05), math.log(0.01)
    cfg = dataclasses.replace(
        base, rl=with_learning(base.rl, init_log_std=init, final_log_std=final, anneal_steps=32),
    )  # fmt: skip
    run = tmp_path / "anneal"
    run_training(cfg, run, progress=False, log=lambda _: None)
    acc = EventAccumulator(str(run))
    acc.Reload()
    stds = [e.value for e in acc.Scalars("Policy / Standard deviation")]
    # updates after steps 31 and 63 sample at the ceiling of that step (0.0105, then the
    # floor 0.01), while the free parameter (~0.05 after two updates) would give ~0.05
    from sonogym.agents.networks import log_std_ceiling

    expected = [math.exp(log_std_ceiling(t, init, final, 32)) for t in (31, 63)]
    assert stds == pytest.approx(expected, rel=1e-5)
    policy, _ = load_policy(run, run / "checkpoints" / "agent_0.pt")
    x = torch.zeros(2, policy.encoder.layout.size)
    log_std0 = policy.compute({"observations": x}, role="policy")[1]["log_std"]
    assert torch.allclose(log_std0, torch.full_like(log_std0, init))  # step 0: no narrowing yet
    policy, _ = load_policy(run)
    log_std = policy.compute({"observations": x}, role="policy")[1]["log_std"]
    assert log_std.max() <= final + 1e-6
    assert policy.log_std.detach().max() > final + 0.5  # the parameter itself is not clamped

    bad = with_learning(cfg.rl, final_log_std=math.log(0.1))
    with pytest.raises(ValueError, match="final_log_std .* above init_log_std"):
        dataclasses.replace(cfg, rl=bad)


def test_observation_statistics_freeze_after_standardize_steps(tmp_path):
    import dataclasses

    from sonogym.agents.configs import resolve_train_config
    from sonogym.agents.train import run_training

    torch.set_num_threads(1)
    assert task_config("surgery").learning.standardize_steps == 30_000
    base = resolve_train_config(
        "surgery", "ppo", preset="cpu", envs=4, steps=32, checkpoint_interval=16,
        env_kwargs=dict(patients=(0,), phantom_spacing=0.002, obs_mode="state",
                        episode_length=16),
    )  # fmt: skip
    cfg = dataclasses.replace(base, rl=with_learning(base.rl, standardize_steps=16))
    run = tmp_path / "frozen"
    run_training(cfg, run, progress=False, log=lambda _: None)
    at16 = read_checkpoint(run / "checkpoints" / "agent_16.pt")["obs_standardizer"]
    at32 = read_checkpoint(run / "checkpoints" / "agent_32.pt")["obs_standardizer"]
    assert at16["count"] == 16 * 4 + 4  # the first reset's observations and 16 steps
    for k in ("count", "mean", "var"):  # then frozen
        assert torch.equal(at16[k], at32[k])
    with pytest.raises(ValueError, match="standardize_steps must be an integer >= 0"):
        dataclasses.replace(base, rl=with_learning(base.rl, standardize_steps=-1))


def test_kl_threshold_follows_sigma_when_asked(tmp_path, monkeypatch):
    import dataclasses

    from skrl.resources.schedulers.torch import KLAdaptiveLR

    from sonogym.agents.configs import resolve_train_config
    from sonogym.agents.train import kl_threshold_at, run_training

    torch.set_num_threads(1)
    rl, ppo = task_config("surgery", preset="cpu"), algo_config("surgery", "ppo", "cpu")
    base_kl = ppo.kl_threshold
    assert not rl.learning.kl_follows_sigma and kl_threshold_at(ppo, rl.learning, 10**6) == base_kl
    on = with_learning(rl, kl_follows_sigma=True).learning
    # the threshold bounds the same mean step at every sigma: x (sigma_0 / ceiling)^2
    assert kl_threshold_at(ppo, on, 0) == pytest.approx(base_kl)
    end = kl_threshold_at(ppo, on, on.anneal_steps)
    assert end == pytest.approx(base_kl * (0.05 / 0.005) ** 2)
    assert kl_threshold_at(ppo, on, 10 * on.anneal_steps) == pytest.approx(end)
    mid = kl_threshold_at(ppo, on, on.anneal_steps // 2)
    assert mid == pytest.approx(base_kl * 10.0)  # geometric: sqrt(100)
    no_anneal = dataclasses.replace(on, final_log_std=None)
    assert kl_threshold_at(ppo, no_anneal, 10**6) == base_kl

    # ... and the training loop hands it to skrl's scheduler before every update
    seen = []
    real_step = KLAdaptiveLR.step

    def step(self, kl=None, **kw):
        if kl is not None:  # (torch's base class steps once, without a KL, while constructing)
            seen.append(self.kl_threshold)
        return real_step(self, kl, **kw)

    monkeypatch.setattr(KLAdaptiveLR, "step", step)
    base = resolve_train_config(
        "surgery", "ppo", preset="cpu", envs=4, steps=32, checkpoint_interval=32,
        env_kwargs=dict(patients=(0,), phantom_spacing=0.002, obs_mode="state",
                        episode_length=16),
    )  # fmt: skip
    fast = with_learning(base.rl, kl_follows_sigma=True, anneal_steps=32)
    fast_ppo = dataclasses.replace(base.params, rollouts=8)
    run_training(dataclasses.replace(base, rl=fast, params=fast_ppo), tmp_path / "kl",
                 progress=False, log=lambda _: None)  # fmt: skip
    updates = [t for t in range(32) if (t + 1) % 8 == 0]
    epochs = fast_ppo.learning_epochs
    want = [kl_threshold_at(fast_ppo, fast.learning, t) for t in updates for _ in range(epochs)]
    assert seen == pytest.approx(want)
    assert seen[-1] > 50 * base_kl
