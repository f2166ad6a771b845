"""Device presets: what `sonogym train` resolves on a CPU or GPU machine, in which order, and
how the resolved config travels through config.json."""

from __future__ import annotations

import json
import math

import pytest

from sonogym.agents.algorithms import algo_config
from sonogym.agents.configs import TrainConfig, resolve_train_config
from sonogym.agents.presets import cpu_threads, resolve_preset
from sonogym.agents.task_defaults import training_defaults


@pytest.mark.parametrize(
    "device, cores, name, envs, net, threads",
    [
        ("cpu", 2, "cpu", 64, "small", 1),  # a second intra-op thread slows a busy 2-core box
        ("cpu", 1, "cpu", 64, "small", 1),
        ("cpu", 16, "cpu", 64, "small", 4),
        ("cuda", 2, "paper", 128, "paper", None),
        ("cuda:1", 16, "paper", 128, "paper", None),
    ],
)
def test_auto_preset_follows_the_device(device, cores, name, envs, net, threads):
    p = resolve_preset("auto", device, cores=cores)
    assert (p.name, p.num_envs, p.net, p.threads) == (name, envs, net, threads)


def test_named_presets_and_image_pooling():
    cpu, paper = resolve_preset("cpu", "cuda", cores=2), resolve_preset("paper", "cpu")
    assert cpu.name == "cpu" and paper.name == "paper"  # a named preset ignores the device
    assert cpu.obs_downsample(200) == 4 and cpu.obs_downsample(50) == 1  # ~50 px of depth
    assert paper.obs_downsample(200) == 1 and cpu.obs_downsample(None) == 1
    assert cpu_threads(2) == 1 and cpu_threads(3) == 3 and cpu_threads(64) == 4
    with pytest.raises(ValueError, match="unknown preset 'gpu'"):
        resolve_preset("gpu")


def test_cpu_preset_resolves_per_task():
    nav = resolve_train_config("navigation", "ppo", preset="auto", device="cpu")
    assert nav.preset == "cpu" and nav.rl.num_envs == 64 and nav.rl.net == "small"
    assert nav.rl.obs_downsample == 4  # 200 px of depth pooled to 50
    surg = resolve_train_config("surgery", "ppo", preset="cpu")
    assert surg.rl.obs_downsample == 1  # the 3-D volume is 50 px deep already
    assert surg.params == training_defaults("surgery").cpu.algorithms["ppo"]  # its CPU table
    assert surg.params != algo_config("surgery", "ppo")
    paper = resolve_train_config("surgery", "ppo", preset="paper")
    assert paper.params == algo_config("surgery", "ppo")  # the paper's table
    assert (paper.rl.num_envs, paper.rl.net, paper.threads) == (128, "paper", None)


def test_cpu_preset_env_options_are_the_tasks_and_explicit_ones_win():
    # the cpu preset trains surgery with w5 = 50 per rad; the env's default and the paper
    # preset keep the paper's 5 (docs/design.md)
    from sonogym.envs.surgery import SurgeryConfig

    assert SurgeryConfig().w5 == 5.0
    cpu = resolve_train_config("surgery", "ppo", preset="cpu")
    box = (0.005, 0.005, 0.01, 0.02, 0.02, 0.001)  # m x3, rad x3: what the drill arm realises
    recipe = {"w5": 50.0, "unsafe_distance_penalty": 100.0, "action_limit": box}
    assert cpu.rl.env_kwargs == training_defaults("surgery").cpu.env_kwargs == recipe
    assert resolve_train_config("surgery", "ppo", preset="paper").rl.env_kwargs == {}
    given = resolve_train_config(
        "surgery", "ppo", preset="cpu", env_kwargs={"w5": 5.0, "obs_mode": "state"}
    )
    assert given.rl.env_kwargs == {
        "w5": 5.0,
        "unsafe_distance_penalty": 100.0,
        "action_limit": box,
        "obs_mode": "state",
    }
    nav = resolve_train_config("navigation", "ppo", preset="cpu")
    assert nav.rl.env_kwargs == {}
    assert resolve_train_config("reconstruction", "ppo", preset="cpu").rl.env_kwargs == {}
    back = TrainConfig.from_dict(json.loads(json.dumps(cpu.to_dict())))
    assert back.rl.env_kwargs == recipe  # config.json records it for eval and resume


@pytest.mark.parametrize(
    "task, obs_mode, published",
    [  # the explicit flags of docs/results.md's runs (sonogym.reproduce recipes)
        ("surgery", "state", dict(net="lean", steps=120_000,
                                  env_kwargs={"unsafe_distance_penalty": 100})),
        ("navigation", None, dict(envs=64, net="small", steps=9024, obs_downsample=4)),
        ("reconstruction", None, dict(envs=64, net="small", steps=4000)),
    ],
)  # fmt: skip
def test_the_cpu_preset_alone_trains_the_published_recipe(task, obs_mode, published):
    obs = {"obs_mode": obs_mode} if obs_mode else {}
    default = resolve_train_config(task, "ppo", preset="cpu", env_kwargs=obs, seed=1)
    env_kwargs = {**published.pop("env_kwargs", {}), **obs}
    explicit = resolve_train_config(
        task, "ppo", preset="cpu", env_kwargs=env_kwargs, seed=1, **published
    )
    assert default.to_dict() == explicit.to_dict()
    paper = resolve_train_config(task, "ppo", preset="paper", env_kwargs=obs, seed=1)
    assert paper.rl.timesteps == training_defaults(task).timesteps  # the paper's own
    assert paper.rl.env_kwargs == obs


@pytest.mark.parametrize("preset", ["cpu", "paper"])
def test_every_preset_keeps_the_tasks_exploration(preset):
    # presets size the machine's share only; the task owns its initial policy std
    surg = resolve_train_config("surgery", "ppo", preset=preset)
    assert surg.rl.learning.init_log_std == pytest.approx(math.log(0.05))
    assert surg.rl.learning.standardize_vectors
    nav = resolve_train_config("navigation", "ppo", preset=preset)
    assert nav.rl.learning == training_defaults("navigation").learning


def test_explicit_options_win_over_preset_and_task():
    cfg = resolve_train_config(
        "navigation", "a2c", preset="cpu", envs=8, steps=500, net="paper", obs_downsample=2,
        threads=2, seed=7, env_kwargs={"patients": [0, 1]},
    )  # fmt: skip
    assert (cfg.rl.num_envs, cfg.steps, cfg.rl.net, cfg.rl.obs_downsample) == (8, 500, "paper", 2)
    assert (cfg.threads, cfg.seed, cfg.preset) == (2, 7, "cpu")
    assert cfg.rl.env_kwargs["patients"] == (0, 1)
    assert cfg.params == algo_config("navigation", "a2c")


def test_train_config_survives_config_json():
    cfg = resolve_train_config(
        "surgery", "ppo-lag", preset="cpu", envs=4, steps=96, seed=3, threads=1,
        env_kwargs={"obs_mode": "state", "patients": [0]}, checkpoint_interval=32,
    )  # fmt: skip
    back = TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg
    assert back.intervals() == cfg.intervals() == (32, cfg.params.rollouts)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(envs=0), "envs must be a positive integer"),
        (dict(steps=-5), "steps must be a positive integer"),
        (dict(obs_downsample=0), "obs_downsample must be a positive integer"),
        (dict(threads=0), "threads must be >= 1"),
        (dict(net="huge"), "unknown net 'huge'"),
        (dict(env_kwargs={"bogus": 1}), r"unknown NavigationConfig option\(s\) \['bogus'\]"),
        (dict(env_kwargs={"w1": float("nan")}), "NavigationConfig.w1 must be a finite number"),
        (dict(env_kwargs={"episode_length": 2.5}), "episode_length must be an integer"),
    ],
)
def test_nonsense_options_are_refused_not_defaulted(kw, message):
    with pytest.raises(ValueError, match=message):
        resolve_train_config("navigation", "ppo", preset="cpu", **kw)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (dict(rollouts=0), r"PPOParams.rollouts must be >= 1, got 0"),
        (dict(mini_batches=2.5), r"PPOParams.mini_batches must be an integer, got 2.5"),
        (dict(learning_rate=0.0), r"PPOParams.learning_rate must be > 0"),
        (dict(learning_rate=math.inf), r"PPOParams.learning_rate must be a finite number"),
        (dict(discount_factor=1.5), r"PPOParams.discount_factor must be in \[0, 1\]"),
        (dict(ratio_clip=-0.2), r"PPOParams.ratio_clip must be >= 0"),
    ],
)
def test_algorithm_tables_refuse_settings_no_run_trains_with(change, message):
    import dataclasses

    ppo = algo_config("navigation", "ppo")
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(ppo, **change)
    a2c = algo_config("navigation", "a2c")
    with pytest.raises(ValueError, match="A2CParams.rollouts must be >= 1"):
        dataclasses.replace(a2c, rollouts=-1)
