"""Differential IK: convergence, velocity-limited tracking lag, limits, unreachable targets."""

from __future__ import annotations

import math

import pytest
import torch

from sonogym.geometry import make_pose, rot_z
from sonogym.robots import DRILL_TOOL, Arm, ArmConfig


def _well_conditioned_targets(arm: Arm, n: int, seed: int, steps_away: float):
    """Random starts 0.25 rad inside the limits and targets at the FK of a configuration at
    most ``steps_away`` control steps of joint motion away, both away from singularities."""
    g = torch.Generator().manual_seed(seed)
    q0 = arm.random_joints(3 * n, g, margin=0.25)
    qt = q0 + (torch.rand(3 * n, 7, generator=g, dtype=q0.dtype) * 2 - 1) * (
        arm.max_joint_step * steps_away
    )
    sigma0 = torch.linalg.svdvals(arm.jacobian(q0))[:, -1]
    sigmat = torch.linalg.svdvals(arm.jacobian(qt))[:, -1]
    keep = ((sigma0 > 0.05) & (sigmat > 0.05)).nonzero()[:, 0][:n]
    assert keep.numel() == n
    tp, tr = arm.fk(qt[keep])
    return q0[keep], tp, tr


@pytest.mark.parametrize(("model", "steps_away"), [("kuka_med14", 4.0), ("franka_fr3", 3.0)])
def test_ik_reaches_512_static_targets_within_10_steps(model, steps_away):
    base = make_pose(rot_z(torch.tensor(0.3)), torch.tensor([-0.4, 0.2, 0.1]))
    arm = Arm(ArmConfig(model=model), base_pose=base)
    q, tp, tr = _well_conditioned_targets(arm, 512, seed=0, steps_away=steps_away)
    first = arm.ik_step(q, tp, tr)
    assert not bool(first.reached.all())  # the targets are really a few steps away
    result = arm.track(q, tp, tr, steps=10)
    assert bool(result.reached.all())
    assert result.pos_error.max() <= 1e-4  # 0.1 mm
    assert result.rot_error.max() <= math.radians(0.1)
    assert not bool(result.unreachable.any())
    # The reported pose is the FK of the returned joints.
    pos, rot = arm.fk(result.q)
    assert torch.allclose(pos, result.pos, atol=1e-6)
    assert torch.allclose(rot, result.rot, atol=1e-6)


def test_fast_command_lags_then_closes():
    arm = Arm(ArmConfig())
    q0 = arm.default_joints(64)
    g = torch.Generator().manual_seed(1)
    # Targets 12 control steps of joint motion away: no single step can reach them.
    delta = (torch.rand(64, 7, generator=g) * 0.5 + 0.5) * arm.max_joint_step * 12
    delta = delta * torch.where(torch.rand(64, 7, generator=g) < 0.5, -1.0, 1.0)
    tp, tr = arm.fk(q0 + delta)
    q, errors = q0, []
    for _ in range(40):
        result = arm.ik_step(q, tp, tr)
        dq = (result.q - q).abs()
        assert bool((dq <= arm.max_joint_step + 1e-6).all())  # joint speed limit held
        assert not bool(result.unreachable.any())  # far is not unreachable
        q = result.q
        errors.append(result.pos_error + arm.config.rotation_weight * result.rot_error)
    e = torch.stack(errors)  # (steps, N)
    assert bool((e[0] > 5e-3).all())  # after one step a tracking error of millimetres remains
    assert bool((e[1:] <= e[:-1] + 1e-6).all())  # it never grows
    assert bool(result.reached.all())  # and it closes


@pytest.mark.parametrize("model", ["kuka_med14", "franka_fr3"])
def test_joint_limits_are_never_exceeded(model):
    arm = Arm(ArmConfig(model=model))
    g = torch.Generator().manual_seed(2)
    n = 256
    q = arm.random_joints(n, g, margin=0.02)
    for _ in range(40):
        # Anything: far, unreachable, or behind the limits (FK of configurations past them).
        wild = arm.q_min + (torch.rand(n, 7, generator=g) * 1.6 - 0.3) * (arm.q_max - arm.q_min)
        tp, tr = arm.fk(wild)
        tp = tp + (torch.rand(n, 3, generator=g) - 0.5) * 2.0
        result = arm.ik_step(q, tp, tr)
        assert bool((result.q >= arm.q_min).all()) and bool((result.q <= arm.q_max).all())
        assert bool(((result.q - q).abs() <= arm.max_joint_step + 1e-6).all())
        assert bool(torch.isfinite(result.q).all())
        q = result.q


def test_unreachable_targets_are_reported_never_nan():
    arm = Arm(ArmConfig(tool=DRILL_TOOL))
    n = 8
    q = arm.default_joints(3 * n)
    ok_p, ok_r = arm.fk(q[:n])  # already there
    far_p = ok_p + torch.tensor([3.0, 0.0, 0.0])  # beyond any reach
    # Tip at the robot's own base with the tool pointing up: inside the arm, not reachable.
    in_p = torch.zeros(n, 3) + torch.tensor([0.0, 0.0, 0.05])
    tp = torch.cat([ok_p, far_p, in_p])
    tr = torch.cat([ok_r, ok_r, torch.eye(3).expand(n, 3, 3)])
    result = arm.track(q, tp, tr, steps=150)
    for t in (result.q, result.pos, result.rot, result.pos_error, result.rot_error):
        assert bool(torch.isfinite(t).all())
    assert bool(result.reached[:n].all()) and not bool(result.unreachable[:n].any())
    assert bool(result.unreachable[n:].all())
    assert bool(result.reachable[:n].all())


def test_singular_start_is_finite_and_converges():
    arm = Arm(ArmConfig(ik_damping=1e-5))  # the reference's reconstruction damping
    q = torch.zeros(4, 7)  # fully stretched: singular
    tp, tr = arm.fk(arm.default_joints(4))  # probe pointing down, 3.1 rad away
    for _ in range(150):
        result = arm.ik_step(q, tp, tr)
        assert bool(torch.isfinite(result.q).all()) and bool(torch.isfinite(result.pos).all())
        assert not bool(result.unreachable.any())  # slow to leave the singularity, not stuck
        q = result.q
    assert bool(result.reached.all())


def test_bad_inputs_raise():
    arm = Arm(ArmConfig())
    q = arm.default_joints(2)
    tp, tr = arm.fk(q)
    with pytest.raises(ValueError, match="NaN"):
        arm.ik_step(q, tp * float("nan"), tr)
    with pytest.raises(ValueError, match="NaN"):
        arm.fk(q * float("nan"))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        arm.ik_step(q, tp[:1], tr)
    with pytest.raises(ValueError, match="joints must be"):
        arm.fk(torch.zeros(2, 6))
    with pytest.raises(ValueError, match="outside the joint limits"):
        arm.ik_step(q + 10.0, tp, tr)
    with pytest.raises(ValueError, match="base pose"):
        Arm(ArmConfig(), base_pose=torch.eye(4).expand(3, 4, 4)).fk(q)
    with pytest.raises(ValueError, match="orthonormal"):
        Arm(ArmConfig(), base_pose=2 * torch.eye(4))
    with pytest.raises(ValueError, match="ik_iterations"):
        ArmConfig(ik_iterations=0)
    with pytest.raises(ValueError, match="init_joints"):
        Arm(ArmConfig(init_joints=(0.0, 3.0, 0.0, 0.0, 0.0, 0.0, 0.0)))


def test_per_arm_base_poses_and_float64():
    bases = make_pose(
        rot_z(torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)),
        torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0.0, 2.0, 0]], dtype=torch.float64),
    )
    arm = Arm(ArmConfig(), base_pose=bases, dtype=torch.float64)
    q = arm.default_joints(3)
    pos, _ = arm.fk(q)
    single = Arm(ArmConfig(), dtype=torch.float64).fk(q)[0]
    expected = (bases[:, :3, :3] @ single.unsqueeze(-1)).squeeze(-1) + bases[:, :3, 3]
    assert torch.allclose(pos, expected)
    result = arm.track(q, pos + 0.01, arm.fk(q)[1], steps=20)
    assert bool(result.reached.all())


def test_reused_frames_give_the_same_steps_and_a_changed_q_is_recomputed():
    # ik_step keeps the FK of the joints it returns, for a loop that passes result.q back;
    # the steps must equal fresh computations, and joints changed in place must not reuse it
    arm = Arm(ArmConfig(model="franka_fr3"))
    q, tp, tr = _well_conditioned_targets(arm, 16, seed=3, steps_away=4.0)
    fresh = Arm(ArmConfig(model="franka_fr3"))
    r = arm.ik_step(q, tp, tr)
    for _ in range(4):
        fresh._last_frames = None  # never reuses
        expected = fresh.ik_step(r.q.clone(), tp, tr)
        assert arm._last_frames is not None and arm._last_frames[0] is r.q
        r = arm.ik_step(r.q, tp, tr)  # first iteration on the kept frames
        for name in ("q", "pos", "rot", "pos_error", "rot_error"):
            assert torch.equal(getattr(r, name), getattr(expected, name)), name
    q_moved = r.q
    q_moved[:, 3] += 0.2  # in place: same tensor object, new version
    expected = fresh.ik_step(q_moved.clone(), tp, tr)
    again = arm.ik_step(q_moved, tp, tr)
    assert torch.equal(again.q, expected.q) and torch.equal(again.pos, expected.pos)
