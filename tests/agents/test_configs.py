"""A run's resolved config: the task's learning record nested in it, the run's own algorithm
config in ``algo_params``, and ``config.json`` files of runs written in earlier layouts (before
the nesting; before the algorithm registry) still loading as the same run."""

import dataclasses
import json

import pytest

from sonogym.agents.algorithms import algo_config
from sonogym.agents.configs import TrainConfig, resolve_train_config, upgrade_config
from sonogym.agents.task_defaults import training_defaults
from sonogym.agents.train import load_train_config
from sonogym.runs import to_jsonable

A2C_TABLE = {"rollouts": 64, "mini_batches": 4, "learning_rate": 1e-4}
SAFETY = {"cost_learning_rate": 1e-4, "cost_threshold": 0.5, "filter_mode": "search",
          "cost_limit": 5.0, "pid_gains": [0.05, 0.0005, 0.1]}  # fmt: skip


def _before_registry(d: dict) -> dict:
    """``to_dict`` in the layout of runs written before the algorithm registry: every
    algorithm's table in ``task_config`` ("ppo", "a2c"), the safe-RL settings in
    ``task_config.safety``, ``algo_params`` the table alone."""
    d = json.loads(json.dumps(to_jsonable(d)))
    params = d["algo_params"]
    table = {k: v for k, v in params.items() if k not in SAFETY}
    safety = {**SAFETY, **{k: v for k, v in params.items() if k in SAFETY}}
    tc = d["task_config"]
    tc["ppo"] = table if d["algo"] != "a2c" else {"rollouts": 32, "learning_epochs": 5,
                                                   "mini_batches": 4, "learning_rate": 3e-4,
                                                   "value_clip": 0.1}  # fmt: skip
    tc["a2c"] = table if d["algo"] == "a2c" else A2C_TABLE
    tc["safety"] = safety
    return {**d, "algo_params": table}


def _flat(d: dict) -> dict:
    """... and before ``learning`` / ``safety`` were nested."""
    tc = dict(d["task_config"])
    tc.update(tc.pop("learning"))
    tc.update(tc.pop("safety"))
    return {**d, "task_config": tc}


def test_task_records_are_nested_not_copied():
    cfg = resolve_train_config("surgery", "ppo-lag", preset="cpu")
    defaults = training_defaults("surgery")
    assert cfg.rl.learning is defaults.learning
    assert (
        cfg.params is defaults.cpu.algorithms["ppo-lag"] is algo_config("surgery", "ppo-lag", "cpu")
    )
    d = cfg.to_dict()
    assert d["task_config"]["learning"]["init_log_std"] == defaults.learning.init_log_std
    assert d["algo_params"]["cost_limit"] == cfg.params.cost_limit == 5.0
    assert "init_log_std" not in d["task_config"] and not {"ppo", "a2c", "safety"} & set(
        d["task_config"]
    )


@pytest.mark.parametrize("algo", ["ppo", "a2c", "ppo-sf", "ppo-lag"])
@pytest.mark.parametrize("older", [_before_registry, lambda d: _flat(_before_registry(d))])
def test_configs_of_earlier_layouts_load_as_the_same_run(algo, older, tmp_path):
    cfg = resolve_train_config("surgery", algo, preset="cpu", envs=4, steps=32, seed=3)
    if algo == "ppo-sf":  # a run's own settings survive, not the defaults
        cfg = dataclasses.replace(cfg, params=dataclasses.replace(cfg.params, cost_threshold=0.3))
    legacy = older(cfg.to_dict())
    assert "ppo" in legacy["task_config"]
    now = json.loads(json.dumps(to_jsonable(cfg.to_dict())))
    assert upgrade_config(legacy) == now
    assert TrainConfig.from_dict(legacy) == cfg
    (tmp_path / "config.json").write_text(json.dumps(legacy))
    assert load_train_config(tmp_path) == cfg


def test_mode_only_observation_scales_join_the_learning_record_of_that_mode_only():
    """``us_memory``'s and ``us_scan``'s motion (m) reaches the network per 10 mm; other modes,
    which have no ``motion`` entry (the adapter refuses scales of unknown entries), keep the
    task's scales."""
    for mode in ("us_memory", "us_scan"):
        memory = resolve_train_config(
            "navigation", "ppo", preset="cpu", env_kwargs={"obs_mode": mode}
        )
        assert memory.rl.learning.obs_scales == {"motion": 100.0}, mode
    for mode in ("us_heading", None):
        kwargs = {} if mode is None else {"obs_mode": mode}
        cfg = resolve_train_config("navigation", "ppo", preset="cpu", env_kwargs=kwargs)
        assert cfg.rl.learning is training_defaults("navigation").learning
        assert "motion" not in cfg.rl.learning.obs_scales
