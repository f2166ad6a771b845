"""The probe's contact force as an env option (``contact_force``, ``force_action``,
``force_limit``): static tissue by default, bit for bit; compression that grows with the
force, reported in ``info`` with a cost past the limit; a force action within its range; bad
values refused by the config and the command line, naming the option; the benchmark identity
telling compressed results apart."""

from __future__ import annotations

import sys

import pytest
import torch

import sonogym  # noqa: F401
from sonogym.cli import main
from sonogym.envs.identity import IdentityMismatch, check_one_identity, identity, stamp
from sonogym.envs.registry import env_config, make_vec
from sonogym.ultrasound.compression import COMPRESSION_VERSION, MAX_CONTACT_FORCE

FAST = dict(patients=(0,), phantom_spacing=0.002)
TISSUE_KEYS = {"contact_force", "compression_mm", "force_cost"}


def _rollout(task: str, steps: int = 3, **kw):
    """Observations and infos of a seeded reset and ``steps`` seeded random steps."""
    env = make_vec(task, 2, **FAST, **kw)
    obs, info = env.reset(seed=0)
    out = [(obs, info)]
    g = torch.Generator().manual_seed(1)
    moves = len(env.cfg.action_scale)  # the motion's components, drawn alike in every variant
    lo, hi = (torch.as_tensor(b)[:, :moves] for b in (env.action_space.low, env.action_space.high))
    for _ in range(steps):
        a = lo + (hi - lo) * torch.rand(lo.shape, generator=g)
        if env.action_space.shape[1] > moves:  # a force action: keep the force at 0
            a = torch.cat([a, -torch.ones(len(a), 1)], 1)
        obs, _, _, _, info = env.step(a)
        out.append((obs, info))
    return env, out


def _images(obs):
    return obs["image"] if isinstance(obs, dict) else obs


@pytest.mark.parametrize(
    "task, obs_mode",
    [("navigation", "us"), ("navigation", "labels"), ("surgery", "us"), ("surgery", "labels")],
)
def test_static_tissue_is_the_default_bit_for_bit(task, obs_mode):
    """Not passing the option, contact_force=0, and (navigation) a force action held at 0 N
    give the same observations, bit for bit, and an info without the force's entries."""
    _, plain = _rollout(task, obs_mode=obs_mode)
    variants = [dict(contact_force=0.0)]
    if task == "navigation":
        variants.append(dict(force_action=True))
    for kw in variants:
        env, other = _rollout(task, obs_mode=obs_mode, **kw)
        for (o0, i0), (o1, i1) in zip(plain, other, strict=True):
            assert torch.equal(_images(o0), _images(o1)), kw
            if "force_action" not in kw:
                assert set(i0) == set(i1) and not TISSUE_KEYS & set(i1)
                assert torch.equal(i0["cost"], i1["cost"])
    if task == "navigation":  # the force action's envs stayed at 0 N and say so
        assert torch.equal(other[-1][1]["contact_force"], torch.zeros(2))


def test_contact_force_compresses_the_tissue_and_info_reports_it():
    env0, plain = _rollout("navigation", steps=1, obs_mode="labels")
    env, pressed = _rollout("navigation", steps=1, obs_mode="labels", contact_force=12.0)
    assert env.scene.tissue is not None and env0.scene.tissue is None
    for (o0, _), (o1, info) in zip(plain, pressed, strict=True):
        assert not torch.equal(o0, o1)  # the tissue moved
        assert torch.equal(info["contact_force"], torch.full((2,), 12.0))
        assert bool((info["compression_mm"] > 0.5).all()) and bool(
            (info["compression_mm"] < 30).all()
        )
        assert torch.equal(info["force_cost"], torch.zeros(2))
        assert torch.equal(info["cost"], info["force_cost"])
    # past the limit: a cost of 1, which is navigation's cost (for PPO-Lagrangian)
    _, over = _rollout("navigation", steps=1, obs_mode="state", contact_force=12.0,
                       force_limit=10.0)  # fmt: skip
    info = over[-1][1]
    assert torch.equal(info["force_cost"], torch.ones(2)) and torch.equal(info["cost"], info[
        "force_cost"])  # fmt: skip
    # state mode images nothing, yet reports the compression of the same poses
    assert torch.allclose(info["compression_mm"], pressed[-1][1]["compression_mm"], atol=1e-4)


def test_compression_grows_monotonically_with_force():
    env = make_vec("navigation", 1, obs_mode="state", force_action=True, **FAST)
    _, info = env.reset(seed=0)
    last = float(info["compression_mm"][0])
    assert last == 0.0
    a = torch.tensor([[0.0, 0.0, 0.0, 2.0]])
    for _ in range(15):
        _, _, _, _, info = env.step(a)
        now = float(info["compression_mm"][0])
        assert now > last, (float(info["contact_force"][0]), now, last)
        last = now


def test_the_force_action_moves_the_force_within_its_range():
    env = make_vec("reconstruction", 2, obs_mode="state", force_action=True, contact_force=5.0,
                   **FAST)  # fmt: skip
    assert env.single_action_space.shape == (5,)
    _, info = env.reset(seed=0)
    assert torch.equal(info["contact_force"], torch.full((2,), 5.0))
    a = torch.zeros(2, 5)
    a[:, 4] = torch.tensor([1.5, -2.0])  # +1.5 N and -2 N per step
    _, _, _, _, info = env.step(a)
    assert torch.allclose(info["contact_force"], torch.tensor([6.5, 3.0]))
    a[:, 4] = torch.tensor([50.0, -50.0])  # clipped to 2 N per step
    _, _, _, _, info = env.step(a)
    assert torch.allclose(info["contact_force"], torch.tensor([8.5, 1.0]))
    for _ in range(15):
        _, _, _, _, info = env.step(a)
    assert torch.allclose(info["contact_force"], torch.tensor([MAX_CONTACT_FORCE, 0.0]))
    assert torch.equal(info["force_cost"], torch.tensor([1.0, 0.0]))  # limit 20 N
    env.reset(options={"reset_mask": torch.tensor([True, False])})
    assert torch.allclose(env.scene.contact_force, torch.tensor([5.0, 0.0]))
    # the task's heuristic holds the force
    from sonogym.envs.reconstruction import heuristic_raster

    assert heuristic_raster(env)[:, 4].abs().max() == 0.0


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf"), MAX_CONTACT_FORCE + 0.5])
@pytest.mark.parametrize("task", ["navigation", "reconstruction", "surgery"])
def test_a_bad_contact_force_is_refused_naming_the_option(task, value):
    with pytest.raises(ValueError, match="contact_force"):
        env_config(task, {"contact_force": value})
    with pytest.raises(ValueError, match="contact_force"):
        make_vec(task, 1, contact_force=value, **FAST)


def test_the_command_line_refuses_a_negative_force_in_one_line(tmp_path, monkeypatch, capsys):
    args = ["train", "--task", "navigation", "--env-option", "contact_force=-1",
            "--out", str(tmp_path / "run")]  # fmt: skip
    monkeypatch.setattr(sys, "argv", ["sonogym", *args])
    with pytest.raises(SystemExit) as e:
        main()
    assert e.value.code != 0
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("sonogym: error: "), lines
    assert "contact_force=-1" in lines[0] and "between 0 and 30 N" in lines[0]
    assert not (tmp_path / "run").exists()


def test_the_identity_records_compressed_tissue_and_tables_keep_it_apart():
    static = identity("navigation")
    assert "tissue" not in static
    assert identity("navigation", {"contact_force": 0.0}) == static
    pressed = identity("navigation", {"contact_force": 10})
    assert pressed["tissue"] == {
        "version": COMPRESSION_VERSION, "contact_force_n": 10.0, "force_action": False,
    }  # fmt: skip
    driven = identity("reconstruction", {"force_action": True})
    assert driven["tissue"]["force_action"] and driven["tissue"]["contact_force_n"] == 0.0
    assert "tissue compressed" in stamp(pressed) and "tissue" not in stamp(static)
    with pytest.raises(IdentityMismatch, match="pressed has tissue"):
        check_one_identity({"static": static, "pressed": pressed})
    with pytest.raises(IdentityMismatch, match="contact_force_n': 20.0"):
        check_one_identity({"a": pressed, "b": identity("navigation", {"contact_force": 20})})
    assert check_one_identity({"a": pressed, "b": dict(pressed)})["tissue"] == pressed["tissue"]
