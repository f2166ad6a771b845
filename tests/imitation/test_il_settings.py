"""What ``sonogym il-train``'s options resolve to: a new run's defaults, and a resumed run
continuing as it was trained for what is left out."""

import pytest

from sonogym.imitation.policies.registry import make_config
from sonogym.imitation.train import il_train_settings, parse_image_size


def test_new_run_defaults():
    s = il_train_settings("act")
    assert (s["size"], s["steps"], s["batch_size"], s["seed"]) == ("cpu", 10_000, 8, 1000)
    assert s["policy_config"] is None  # ILTrainConfig makes the size's config
    s = il_train_settings("act", size="paper", image_size="100x75")
    assert s["policy_config"] == make_config("act", "paper", image_size=(100, 75))


def test_resumed_run_keeps_what_is_left_out():
    trained = make_config("act", "paper")
    old = {"policy": "act", "seed": 7, "train": {"batch_size": 4, "steps": 50},
           "policy_config": trained.to_dict()}  # fmt: skip
    s = il_train_settings("act", old, steps=80)
    assert (s["steps"], s["batch_size"], s["seed"]) == (80, 4, 7)
    assert s["policy_config"] == trained  # not the cpu size a new run would take
    assert il_train_settings("act", old, size="cpu")["policy_config"] is None


def test_image_size_text():
    assert parse_image_size("50X37") == (50, 37)
    for bad in ("100", "0x5", "ax3"):
        with pytest.raises(ValueError, match="HxW in pixels"):
            parse_image_size(bad)


def test_a_config_with_the_former_cpu_preset_name_is_refused():
    import dataclasses
    from typing import Any, ClassVar

    from sonogym.imitation.policies.act import ACTConfig

    with pytest.raises(TypeError, match="CPU_PRESET is not read: name it CPU_SIZE"):

        @dataclasses.dataclass(frozen=True)
        class OldStyle(ACTConfig):
            CPU_PRESET: ClassVar[dict[str, Any]] = dict(chunk_size=3, n_action_steps=3)
