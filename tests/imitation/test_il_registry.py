"""The imitation-policy registry: a policy defined outside sonogym and registered with one
``register`` call trains with ``sonogym il-train``, acts through the env-side wrapper with the
observation history it declares, and is evaluated by ``sonogym eval --run``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any, ClassVar

import pytest
import torch
from typer.testing import CliRunner

from sonogym.cli import app
from sonogym.evaluation.curves import algo_label
from sonogym.evaluation.trained import load_run
from sonogym.imitation import record as rec
from sonogym.imitation.policies.base import ILConfig, ILModel
from sonogym.imitation.policies.registry import (
    PolicySpec,
    get_policy,
    policy_names,
    register,
    unregister,
)
from sonogym.imitation.processor import ACTION_KEY, PolicyFeatures

IMAGE = "observation.images.us"


@dataclass(frozen=True)
class MeanBrightnessConfig(ILConfig):
    """A linear map from the mean brightness of the last ``history`` images to a chunk."""

    CPU_SIZE: ClassVar[dict[str, Any]] = dict(chunk=3)

    history: int = 2  # observations read, >= 1
    chunk: int = 5  # actions per prediction
    n_action_steps: int = 2
    lr: float = 1e-2
    grad_clip_norm: float = 1.0
    visual_norm: str = "identity"
    state_norm: str = "mean_std"
    action_norm: str = "mean_std"

    def delta_indices(self, features: PolicyFeatures) -> dict[str, list[int]]:
        obs = list(range(1 - self.history, 1))
        return {**{k: obs for k in features.image_keys}, ACTION_KEY: list(range(self.chunk))}

    @property
    def observation_steps(self) -> int:
        return self.history

    @property
    def chunk_length(self) -> int:
        return self.chunk


class MeanBrightnessModel(ILModel):
    seen: ClassVar[list[tuple[int, ...]]] = []  # shapes of the images predict() was given

    def __init__(self, config, features, stats):
        super().__init__(config, features, stats)
        self.head = torch.nn.Linear(config.history, config.chunk * features.action_dim)

    def _chunk(self, images: torch.Tensor) -> torch.Tensor:
        x = self.head(images.mean(dim=(-3, -2, -1)))  # (B, history) -> (B, chunk * A)
        return x.view(len(x), self.config.chunk, self.features.action_dim)

    def loss(self, batch, generator):
        err = (self._chunk(batch[IMAGE]) - batch[ACTION_KEY]).abs()
        l1 = (err * ~batch[ACTION_KEY + "_is_pad"][..., None]).mean()
        return l1, {"l1": float(l1.detach())}

    def predict(self, obs, generator):
        MeanBrightnessModel.seen.append(tuple(obs[IMAGE].shape))
        return self._chunk(obs[IMAGE])

    def optimizer(self):
        return torch.optim.SGD(self.parameters(), lr=self.config.lr)


@pytest.fixture
def brightness_policy():
    spec = register(
        PolicySpec("brightness", MeanBrightnessConfig, MeanBrightnessModel, "bright", "Bright")
    )
    MeanBrightnessModel.seen.clear()
    yield spec
    unregister("brightness")


def test_a_registered_policy_trains_and_is_evaluated_through_the_commands(
    brightness_policy, tmp_path
):
    torch.set_num_threads(1)
    data, run = tmp_path / "data", tmp_path / "run"
    rec.record("navigation", data, episodes=2, envs=2, progress=False, log=lambda m: None,
               env_kwargs=dict(phantom_spacing=0.002, episode_length=30))  # fmt: skip
    runner = CliRunner()
    args = ["il-train", "--policy", "brightness", "--data", str(data), "--out", str(run),
            "--steps", "4", "--batch-size", "4", "--threads", "1"]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    cfg = json.loads((run / "config.json").read_text())
    assert (cfg["policy"], cfg["algo"], cfg["task"]) == ("brightness", "bright", "navigation")
    assert cfg["policy_config"] == MeanBrightnessConfig.cpu().to_dict()
    assert cfg["policy_config"]["chunk"] == 3  # il-train's default size: cpu
    assert load_run(run).algo == "bright" and algo_label("bright") == "Bright"

    res = runner.invoke(app, ["eval", "--run", str(run), "--trials", "2", "--envs", "2"])
    assert res.exit_code == 0, res.output
    results = json.loads((run / "eval.json").read_text())["results"]
    assert set(results) == {"policy", "expert", "random"}
    assert "| policy |" in (run / "eval.md").read_text()
    # the wrapper kept the two-image history the config declares, batched over the 2 envs
    assert MeanBrightnessModel.seen and set(MeanBrightnessModel.seen) <= {
        (2, 2, 1, 200, 150),
        (1, 2, 1, 200, 150),
    }


def test_names_and_algorithms_are_unique_and_unknown_ones_are_named(brightness_policy):
    assert policy_names() == ("act", "diffusion", "brightness")
    assert get_policy("diffusion").algo == "dp" and algo_label("dp") == "DP"
    for clash in (
        PolicySpec("act", MeanBrightnessConfig, MeanBrightnessModel, "other", "Other"),
        PolicySpec("other", MeanBrightnessConfig, MeanBrightnessModel, "dp", "Other"),
    ):
        with pytest.raises(ValueError, match="clashes with the registered"):
            register(clash)
    with pytest.raises(ValueError, match=r"unknown policy 'bc'; choose one of \('act'"):
        get_policy("bc")
    unregister("brightness")
    with pytest.raises(ValueError, match="policy 'brightness' unknown"):
        CliRunner().invoke(app, ["il-train", "--policy", "brightness", "--data", "d", "--out",
                                 "o", "--threads", "1"], catch_exceptions=False)  # fmt: skip
    register(brightness_policy)  # for the fixture's clean-up
