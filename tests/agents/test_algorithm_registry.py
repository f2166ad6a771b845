"""The RL algorithm registry: an algorithm defined outside sonogym and registered with one
``register`` call trains with ``sonogym train``, takes ``--set`` settings, records its config
in the run, is evaluated by ``sonogym eval`` with the controllers it adds, and is labelled in
plots; unknown algorithms and unsupported pairs are named, never given PPO's settings."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import pytest
import torch
from typer.testing import CliRunner

from sonogym.agents.algorithms import (
    Acting,
    ActingSetup,
    AgentSetup,
    AlgorithmSpec,
    algo_config,
    algorithm_names,
    check_algo,
    get_algorithm,
    register,
    task_algorithms,
    unregister,
)
from sonogym.agents.algorithms.ppo import PPO_ALGORITHM
from sonogym.agents.task_defaults import training_defaults
from sonogym.cli import app
from sonogym.envs.policy import StatelessPolicy
from sonogym.envs.registry import task_names
from sonogym.evaluation.curves import algo_label
from sonogym.evaluation.trained import load_run


@dataclass(frozen=True)
class NudgeConfig:
    """Vanilla policy gradient: one SGD step per update on the log-likelihood of the rollout's
    actions weighted by their reward above the rollout's mean."""

    rollouts: int = 8  # env steps per env between updates
    mini_batches: int = 1  # the whole rollout in one batch
    learning_rate: float = 1e-3  # SGD, per update


class NudgeAgent:
    """A minimal skrl agent: what the trainer calls, and nothing else."""

    def __new__(cls, setup: AgentSetup):
        from skrl.agents.torch import Agent, AgentCfg, ExperimentCfg

        class _Nudge(Agent):
            def __init__(self, setup: AgentSetup) -> None:
                experiment = ExperimentCfg(
                    directory=str(setup.out.parent), experiment_name=setup.out.name,
                    write_interval=setup.write_interval, checkpoint_interval=0,
                )  # fmt: skip
                super().__init__(
                    cfg=AgentCfg(experiment=experiment), models=setup.models,
                    observation_space=setup.observation_space, action_space=setup.action_space,
                    device=setup.device,
                )  # fmt: skip
                self.config = setup.config
                self.policy = self.models["policy"]
                self.optimizer = torch.optim.SGD(
                    self.policy.parameters(), lr=self.config.learning_rate
                )
                self.checkpoint_modules.update(policy=self.policy, optimizer=self.optimizer)
                self.rollout: list[tuple[torch.Tensor, ...]] = []
                self.updates = 0

            def act(self, observations, states, *, timestep, timesteps):
                return self.policy.act({"observations": observations}, role="policy")[:2]

            def record_transition(self, *, observations, actions, rewards, **kwargs):
                super().record_transition(observations=observations, actions=actions,
                                          rewards=rewards, **kwargs)  # fmt: skip
                self.rollout.append((observations, actions, rewards.view(-1)))

            def pre_interaction(self, *, timestep, timesteps):
                pass

            def post_interaction(self, *, timestep, timesteps):
                if len(self.rollout) == self.config.rollouts:
                    self.update(timestep=timestep, timesteps=timesteps)
                super().post_interaction(timestep=timestep, timesteps=timesteps)

            def update(self, *, timestep, timesteps):
                obs, actions, rewards = (torch.cat(x) for x in zip(*self.rollout, strict=True))
                self.rollout.clear()
                inputs = {"observations": obs, "taken_actions": actions}
                log_prob = self.policy.act(inputs, role="policy")[1]["log_prob"].view(-1)
                loss = -(log_prob * (rewards - rewards.mean())).mean()
                self.optimizer.zero_grad()
                loss.backward()
                self.optimizer.step()
                self.updates += 1
                self.track_data("Loss / Nudge loss", loss.item())

        return _Nudge(setup)


class StandStill(StatelessPolicy):
    """An extra evaluation controller the algorithm adds: no motion."""

    def __init__(self, policy) -> None:
        self.policy = policy

    def act(self, obs, info):
        return torch.zeros_like(self.policy.act(obs, info))


def nudge_acting(setup: ActingSetup):
    return StandStill(setup.policy) if setup.controller == "still" else setup.policy


NUDGE = AlgorithmSpec(
    name="nudge",
    label="Nudge",
    config_cls=NudgeConfig,
    build=NudgeAgent,
    acting=Acting(policy=nudge_acting, controllers=("still",)),
    defaults={"navigation": NudgeConfig()},  # the task it runs on, with its settings there
)


@pytest.fixture
def nudge():
    spec = register(NUDGE)
    yield spec
    unregister("nudge")


def test_a_registered_algorithm_trains_and_is_evaluated_through_the_commands(nudge, tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    runner = CliRunner()
    args = ["train", "--task", "navigation", "--algo", "nudge", "--obs-mode", "state",
            "--envs", "2", "--steps", "16", "--threads", "1", "--phantom-spacing", "2",
            "--env-option", "episode_length=8", "--set", "nudge.learning_rate=0.01",
            "--out", str(run)]  # fmt: skip
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    cfg = json.loads((run / "config.json").read_text())
    assert (cfg["task"], cfg["algo"]) == ("navigation", "nudge")
    assert cfg["algo_params"] == {"rollouts": 8, "mini_batches": 1, "learning_rate": 0.01}
    first = torch.load(run / "checkpoints" / "agent_0.pt", weights_only=True)
    last = torch.load(run / "checkpoints" / "agent_16.pt", weights_only=True)
    assert set(last) == {"policy", "optimizer"}  # what the agent checkpoints
    assert not torch.equal(first["policy"]["mean_head.weight"], last["policy"]["mean_head.weight"])
    assert load_run(run).algo == "nudge" and algo_label("nudge") == "Nudge"

    res = runner.invoke(app, ["eval", "--run", str(run), "--trials", "2", "--envs", "2"])
    assert res.exit_code == 0, res.output
    table = json.loads((run / "eval.json").read_text())
    # the controller the algorithm adds runs right after the policy, from the same starts
    assert list(table["results"]) == ["policy", "still", "expert", "random"]
    assert "| still |" in (run / "eval.md").read_text()
    with pytest.raises(ValueError, match=r"apply to ppo-sf runs; .* is a nudge run"):
        from sonogym.evaluation.rl_eval import evaluate_run

        evaluate_run(run, trials=1, envs=1, safety_filter={"mode": "zero"})


def test_unknown_algorithms_and_unsupported_pairs_are_named_never_defaulted(nudge, tmp_path):
    assert algorithm_names() == ("ppo", "a2c", "ppo-sf", "ppo-lag", "nudge")
    assert task_algorithms("navigation") == ("ppo", "a2c", "nudge")
    assert task_algorithms("surgery") == ("ppo", "a2c", "ppo-sf", "ppo-lag")
    assert algo_config("navigation", "nudge") == NudgeConfig()
    known = r"known algorithms: \['ppo', 'a2c', 'ppo-sf', 'ppo-lag', 'nudge'\]"
    with pytest.raises(ValueError, match=rf"unknown algorithm 'sac'; {known}"):
        algo_config("navigation", "sac")
    with pytest.raises(ValueError, match=rf"unknown algorithm 'sac'; {known}"):
        get_algorithm("sac")
    with pytest.raises(ValueError, match=r"'nudge' is not supported on surgery; supported: \["):
        check_algo("surgery", "nudge")
    with pytest.raises(ValueError, match="registered already"):
        register(dataclasses.replace(PPO_ALGORITHM))
    with pytest.raises(TypeError, match=r"lacks \['rollouts', 'mini_batches'\]"):
        AlgorithmSpec("odd", "Odd", dataclass(frozen=True)(type("Odd", (), {})), NudgeAgent)
    with pytest.raises(TypeError, match="not a NudgeConfig"):
        AlgorithmSpec("odd", "Odd", NudgeConfig, NudgeAgent, defaults={"navigation": object()})

    runner = CliRunner()
    res = runner.invoke(app, ["train", "--task", "navigation", "--algo", "sac",
                              "--out", str(tmp_path / "a")])  # fmt: skip
    text = " ".join(res.output.split())
    assert res.exit_code != 0 and "unknown algorithm 'sac'" in text, text
    res = runner.invoke(app, ["train", "--task", "navigation", "--set", "nudge.learning_rate=1",
                              "--out", str(tmp_path / "b")])  # fmt: skip
    text = " ".join(f"{res.output} {res.exception!r}".split())
    assert res.exit_code != 0 and "a nudge setting, but this run trains ppo" in text, text
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_every_task_configures_registered_algorithms_with_their_own_classes():
    """Each task's agents module names registered algorithms only, each with a config of its
    class; the safe-RL algorithms only where the env has a cost."""
    for task in task_names():
        defaults = training_defaults(task)
        for recipe in (defaults.algorithms, defaults.cpu.algorithms):
            for algo, config in recipe.items():
                assert isinstance(config, get_algorithm(algo).config_cls), (task, algo)
    assert task_algorithms("navigation") == task_algorithms("reconstruction") == ("ppo", "a2c")
