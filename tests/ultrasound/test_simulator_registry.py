"""The simulator registry: the built-in simulators by name, a former name, an unknown one
refused, and a simulator registered here, outside the package, running an env, a training run
and an evaluation protocol without any package file knowing it."""

from __future__ import annotations

import json

import pytest
import torch

import sonogym  # noqa: F401
from sonogym.envs.identity import identity
from sonogym.envs.navigation import NavigationConfig, NavigationEnv
from sonogym.ultrasound.registry import (
    SimulatorSpec,
    get_simulator,
    register,
    simulator_names,
    unregister,
)

FAST = dict(patients=(0,), phantom_spacing=0.002, robot=None)
NAME = "ct-window"
#: HU mapped to [0, 1], the envs' "ct" observation's window
WINDOW = (-1000.0, 2000.0)


class CTWindow:
    """A simulator whose image is the CT slice windowed to [0, 1]."""

    def simulate(self, slices):
        lo, hi = WINDOW
        return ((slices.ct - lo) / (hi - lo)).clamp(0, 1)


@pytest.fixture(scope="module")
def ct_window():
    spec = register(
        SimulatorSpec(
            NAME,
            build=lambda patients, device, options: CTWindow(),
            identity=lambda options: {"model": NAME, "version": 1},
            summary="the windowed CT slice",
        )
    )
    yield spec
    unregister(NAME)


def test_builtin_simulators_and_what_they_declare():
    assert simulator_names()[:3] == ("physical", "reference", "learned")
    learned, physical = get_simulator("learned"), get_simulator("physical")
    assert learned.draws_net and learned.needs_volumes and learned.group == "LB"
    assert not physical.draws_net and not physical.needs_volumes and physical.group == "MB"
    assert physical.dynamic_range == 60.0
    assert identity("navigation", {"simulator": "physical"})["ultrasound"] == {
        "model": "physical",
        "version": 1,
    }


def test_an_unknown_name_is_refused_naming_the_registered_ones():
    with pytest.raises(ValueError, match=r"unknown simulator 'ray-tracer'; choose one of .*"
                       r"'physical', 'reference', 'learned'"):  # fmt: skip
        get_simulator("ray-tracer")
    with pytest.raises(ValueError, match="unknown simulator 'ray-tracer'"):
        NavigationConfig(simulator="ray-tracer")
    for taken in ("physical", "sonogym"):
        with pytest.raises(ValueError, match="already registered"):
            register(SimulatorSpec(taken, build=None, identity=None))
    with pytest.raises(ValueError, match="group"):
        SimulatorSpec("x", build=None, identity=None, group="XB")


def test_the_former_reference_name_warns_and_is_replaced():
    with pytest.warns(DeprecationWarning, match="'sonogym' is now called 'reference'.*0.3.0"):
        assert get_simulator("sonogym").name == "reference"
    with pytest.warns(DeprecationWarning):
        assert NavigationConfig(simulator="sonogym").simulator == "reference"


def test_an_env_runs_on_a_simulator_registered_outside_the_package(ct_window):
    torch.set_num_threads(1)
    env = NavigationEnv(2, simulator=NAME, episode_length=5, **FAST)
    obs, _ = env.reset(seed=0)
    assert not env.scene.draws_nets
    g = torch.Generator().manual_seed(0)
    for _ in range(3):
        obs, *_ = env.step(torch.rand(2, 3, generator=g) * 2 - 1)
        assert torch.equal(obs, env.scene.observe("ct"))
    assert identity("navigation", {"simulator": NAME})["ultrasound"] == {
        "model": NAME,
        "version": 1,
    }
    # imaging randomisation applies to its display image (the registry's default)
    env = NavigationEnv(2, simulator=NAME, imaging_randomization=True, **FAST)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (2, 1, 200, 150) and 0 <= float(obs.min()) and float(obs.max()) <= 1


def test_a_run_trains_and_is_evaluated_on_it(ct_window, tmp_path):
    from sonogym.agents.train import train
    from sonogym.evaluation.protocols import ProtocolError, simulator_group
    from sonogym.evaluation.rl_eval import evaluate_run

    torch.set_num_threads(1)
    run = tmp_path / "run"
    env_kwargs = dict(phantom_spacing=0.002, episode_length=6)
    train("navigation", "ppo", envs=2, steps=12, out=run, patients=(0,), simulator=NAME,
          obs_downsample=4, env_kwargs=env_kwargs, progress=False)  # fmt: skip
    res = evaluate_run(run, trials=2, envs=2, protocol="idt", controllers=("expert", "random"),
                       plot=False)  # fmt: skip
    assert set(res) == {"expert", "random"}
    saved = json.loads((run / "eval.json").read_text())
    assert saved["identity"]["ultrasound"] == {"model": NAME, "version": 1}
    assert simulator_group(NAME) == "MB"
    with pytest.raises(ProtocolError, match="learned simulator"):
        evaluate_run(run, trials=2, envs=2, protocol="odt-sim")
