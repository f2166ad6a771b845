"""Per-episode imaging settings in the envs: drawn per env at each reset from the env's seeded
generator, within their ranges; the rest of the episode (starts, nets) unchanged; off unless
asked (both training presets leave it off), never in evaluation."""

from __future__ import annotations

import torch

from sonogym.agents.configs import task_config
from sonogym.envs.registry import make_vec
from sonogym.ultrasound.randomization import ImagingRandomization


def _episode(randomize, seed=4):
    env = make_vec("navigation", 4, phantom_spacing=0.002, imaging_randomization=randomize)
    obs, info = env.reset(seed=seed)
    return env, obs, info


def test_settings_are_drawn_per_env_and_episode_within_their_ranges():
    env, obs, info = _episode(True)
    s = env.scene.imaging_settings.clone()
    ranges = ImagingRandomization()
    for i, name in enumerate(ImagingRandomization.COLUMNS):
        lo, hi = getattr(ranges, name)
        assert (s[:, i] >= lo).all() and (s[:, i] <= hi).all(), name
    assert len(set(s[:, 0].tolist())) == 4  # each env its own gain
    env.reset(options={"reset_mask": torch.tensor([True, False, False, False])})
    t = env.scene.imaging_settings
    assert not torch.equal(t[0], s[0]) and torch.equal(t[1:], s[1:])


def test_same_seed_same_images_and_the_starts_do_not_move():
    env_a, obs_a, info_a = _episode(True)
    _, obs_b, _ = _episode(True)
    env_off, obs_off, info_off = _episode(False)
    assert torch.equal(obs_a, obs_b)  # deterministic
    assert torch.equal(info_a["command"], info_off["command"])  # same starts
    assert not torch.equal(obs_a, obs_off)  # and other images
    assert env_off.scene.imaging_settings is None


def test_off_unless_asked_for_and_always_off_in_evaluation(monkeypatch):
    assert "imaging_randomization" not in task_config("navigation", "cpu").env_kwargs
    assert "imaging_randomization" not in task_config("navigation", "paper").env_kwargs
    import sonogym.envs.registry as registry
    from sonogym.evaluation import rl_eval
    from sonogym.evaluation.trained import TrainedRun

    built = {}

    def spy(task, n, **kw):
        built.update(kw)
        raise RuntimeError("built")

    monkeypatch.setattr(registry, "make_vec", spy)
    run = TrainedRun(path=None, kind="rl", task="navigation", algo="ppo", seed=0,
                     env_kwargs={"imaging_randomization": True}, config={})  # fmt: skip
    try:
        rl_eval.run_controllers(run, trials=2)
    except RuntimeError:
        pass
    assert built["imaging_randomization"] is False
