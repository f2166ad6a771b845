"""A run's resolved config: the task's learning and safety records nested in it, and
``config.json`` files of runs written before the nesting still loading as they were."""

import json

from sonogym.agents.configs import TrainConfig, nested_task_config, resolve_train_config
from sonogym.agents.train import load_train_config
from sonogym.envs.registry import get_task
from sonogym.runs import to_jsonable


def _flat(d: dict) -> dict:
    """``to_dict`` in the layout of runs written before ``learning`` / ``safety`` nesting."""
    tc = dict(d["task_config"])
    tc.update(tc.pop("learning"))
    tc.update(tc.pop("safety"))
    return {**d, "task_config": tc}


def test_task_records_are_nested_not_copied():
    cfg = resolve_train_config("surgery", "ppo-lag", preset="cpu")
    spec = get_task("surgery").training
    assert cfg.rl.learning is spec.learning and cfg.rl.safety is spec.safety
    tc = cfg.to_dict()["task_config"]
    assert tc["learning"]["init_log_std"] == spec.learning.init_log_std
    assert tc["safety"]["cost_limit"] == spec.safety.cost_limit
    assert "init_log_std" not in tc and "cost_limit" not in tc


def test_legacy_flat_config_loads_as_the_same_run(tmp_path):
    cfg = resolve_train_config("surgery", "ppo-sf", preset="cpu", envs=4, steps=32, seed=3)
    legacy = json.loads(json.dumps(to_jsonable(_flat(cfg.to_dict()))))
    assert "learning" not in legacy["task_config"]
    assert nested_task_config(legacy["task_config"]) == json.loads(
        json.dumps(to_jsonable(cfg.to_dict()["task_config"]))
    )
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
        assert cfg.rl.learning is get_task("navigation").training.learning
        assert "motion" not in cfg.rl.learning.obs_scales
