"""The skrl adapter: flat layout, shapes, and stepping identical to the raw env."""

from __future__ import annotations

import pytest
import torch

from sonogym.agents.adapter import SkrlEnvAdapter, obs_layout
from sonogym.envs.navigation import NavigationEnv
from sonogym.envs.reconstruction import ReconstructionEnv
from sonogym.envs.surgery import SurgeryEnv

FAST = dict(patients=(0,), phantom_spacing=0.002)


def test_layout_sorted_keys_and_roundtrip():
    env = ReconstructionEnv(2, **FAST)
    layout = obs_layout(env.single_observation_space)
    assert layout.keys == ("path_length", "reconstruction")  # sorted, skrl's order
    assert layout.size == 1 + 40**3
    flat = torch.arange(2 * layout.size, dtype=torch.float32).view(2, -1)
    parts = layout.unflatten(flat)
    assert parts["path_length"].shape == (2, 1)
    assert parts["reconstruction"].shape == (2, 40, 40, 40)
    assert torch.equal(parts["reconstruction"].reshape(2, -1), flat[:, 1:])
    with pytest.raises(ValueError, match="features"):
        layout.unflatten(flat[:, :-1])


@pytest.mark.parametrize("cls", [NavigationEnv, ReconstructionEnv, SurgeryEnv])
def test_step_matches_raw_env(cls):
    raw, wrapped = cls(2, **FAST), cls(2, **FAST)
    adapter = SkrlEnvAdapter(wrapped, seed=3)
    obs_raw, _ = raw.reset(seed=3)
    obs, _ = adapter.reset()
    assert obs.shape == (2, adapter.layout.size) and obs.dtype == torch.float32
    assert adapter.observation_space.shape == (adapter.layout.size,)
    assert adapter.action_space == raw.single_action_space
    assert adapter.num_envs == 2 and adapter.state() is None
    assert torch.equal(obs, adapter.flatten(obs_raw))
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        a = torch.rand(2, *raw.single_action_space.shape, generator=gen) * 2 - 1
        o1, r1, te1, tr1, _ = raw.step(a)
        o2, r2, te2, tr2, _ = adapter.step(a)
        assert o2.shape == obs.shape and r2.shape == (2, 1)
        assert te2.shape == (2, 1) and tr2.shape == (2, 1) and te2.dtype == torch.bool
        assert torch.equal(o2, adapter.flatten(o1))
        assert torch.equal(r2.view(-1), r1.float())
        assert torch.equal(te2.view(-1), te1) and torch.equal(tr2.view(-1), tr1)
    # skrl's trainer calls reset() again: no per-env reset, the latest observations come back
    again, _ = adapter.reset()
    assert again is o2


def test_downsample_and_scales():
    env = NavigationEnv(2, **FAST)
    adapter = SkrlEnvAdapter(env, obs_downsample=2, seed=0)
    obs, _ = adapter.reset()
    assert adapter.layout.shapes == ((1, 100, 75),)
    img = env._get_observations(None)
    want = torch.nn.functional.avg_pool2d(img, 2).reshape(2, -1)
    assert torch.allclose(obs, want)
    with pytest.raises(ValueError, match="obs_downsample"):
        SkrlEnvAdapter(env, obs_downsample=0)
    rec = ReconstructionEnv(2, **FAST)
    scaled = SkrlEnvAdapter(rec, obs_scales={"path_length": 10.0}, seed=0)
    scaled.reset()
    rec_obs, *_ = scaled.step(torch.ones(2, 4))
    assert torch.allclose(rec_obs[:, 0], rec._get_observations(None)["path_length"][:, 0] * 10)
    with pytest.raises(ValueError, match="unknown entries"):
        SkrlEnvAdapter(rec, obs_scales={"nope": 1.0})


def test_final_observations_substitute_true_final_obs():
    env = NavigationEnv(2, episode_length=2, **FAST)
    adapter = SkrlEnvAdapter(env, obs_downsample=2, seed=0)
    adapter.reset()
    a = torch.ones(2, 3)
    _, _, _, trunc, info = adapter.step(a)
    assert not trunc.any() and "final_obs" not in info
    nxt, _, _, trunc, info = adapter.step(a)
    assert trunc.all()  # SAME_STEP: nxt is the new episode's first observation
    final = adapter.final_observations(info, nxt)
    assert torch.equal(final, adapter.flatten(info["final_obs"]))
    assert not torch.equal(final, nxt)


def test_training_adapter_staggers_the_first_episodes_where_the_task_asks():
    from sonogym.agents.configs import task_config

    assert task_config("surgery").learning.stagger_episodes is True
    assert task_config("navigation").learning.stagger_episodes is False
    for stagger in (True, False):
        env = SurgeryEnv(8, obs_mode="state", **FAST)
        SkrlEnvAdapter(env, seed=0, stagger_episodes=stagger).reset()
        limits = env.time_limit.tolist()
        assert (len(set(limits)) > 1) is stagger
        assert max(limits) <= env.episode_length


def test_training_run_keeps_the_stagger_after_its_cost_estimate(tmp_path, monkeypatch):
    """The announced run measures a few steps first, then resets: the stagger must survive."""
    from sonogym.agents.train import train
    from sonogym.envs.base import TorchVectorEnv

    first_ends: list[int] = []
    step = TorchVectorEnv.step

    def recording_step(self, actions):
        out = step(self, actions)
        if bool(out[3].any()):
            first_ends.append(int(out[3].sum()))
        return out

    monkeypatch.setattr(TorchVectorEnv, "step", recording_step)
    lines: list[str] = []
    train("surgery", "ppo", envs=8, steps=16, out=tmp_path / "run", patients=(0,),
          progress=False, log=lines.append,
          env_kwargs=dict(phantom_spacing=0.002, obs_mode="state", episode_length=16))  # fmt: skip
    assert any("estimated" in s for s in lines)  # the estimate ran
    # staggered: the 8 first episodes end over several steps, not all 8 at step 16
    assert len(first_ends) > 2 and max(first_ends) < 8


def test_privileged_state_is_the_current_state_and_the_transitions_final_one():
    """``state()`` is ``info["state"]`` of the observations the policy acts on (after an
    autoreset: the new episode's first state); ``transition_states`` the state each
    transition reached (an ended episode's final state), as ``final_observations``."""
    env = NavigationEnv(2, episode_length=2, **FAST)
    adapter = SkrlEnvAdapter(env, obs_downsample=2, seed=0, privileged_state=True)
    assert adapter.state_space.shape == (6,)
    _, info = adapter.reset()
    assert torch.equal(adapter.state(), info["state"])
    a = torch.ones(2, 3)
    before = adapter.state()
    _, _, _, trunc, info = adapter.step(a)
    assert not trunc.any()
    assert torch.equal(adapter.state(), info["state"]) and not torch.equal(adapter.state(), before)
    assert torch.equal(adapter.transition_states(info), info["state"])
    _, _, _, trunc, info = adapter.step(a)
    assert trunc.all()
    assert torch.equal(adapter.transition_states(info), info["state"])  # the final states
    assert torch.equal(adapter.state(), env.current_info()["state"])  # the new episodes'
    assert not torch.equal(adapter.state(), info["state"])
    plain = SkrlEnvAdapter(NavigationEnv(2, **FAST), obs_downsample=2, seed=0)
    plain.reset()
    assert plain.state_space is None and plain.state() is None
    assert plain.transition_states(info) is None


def test_privileged_state_needs_the_envs_state():
    with pytest.raises(ValueError, match=r"info\['state'\]"):
        SkrlEnvAdapter._privileged({"command": torch.zeros(2, 3)})
