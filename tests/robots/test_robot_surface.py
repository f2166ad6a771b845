"""Probe held on the skin (SurfaceController) and robot placements relative to the patient."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sonogym.geometry import normalize
from sonogym.robots import (
    DRILL_TOOL,
    NAVIGATION_PROBE_BASE,
    OVERHEAD_PROBE_BASE,
    SURGERY_DRILL_BASE,
    SURGERY_PROBE_BASE,
    Arm,
    ArmConfig,
    BasePlacement,
    SurfaceController,
    reference_base_in_voxel_frame,
)
from sonogym.robots.placement import reference_patient_rotation


def _anchor(skin) -> torch.Tensor:
    """Skin point above L4 (at the origin of the synthetic backs)."""
    return skin.point(torch.zeros(()), torch.zeros(()))


def _controller(skin, placement=NAVIGATION_PROBE_BASE, model="kuka_med14") -> SurfaceController:
    arm = Arm(
        ArmConfig(model=model, init_joints=placement.init_joints),
        base_pose=placement.base_pose(_anchor(skin)),
    )
    return SurfaceController(skin, arm)


def _joint_margin(arm: Arm, q: torch.Tensor) -> torch.Tensor:
    return torch.minimum(q - arm.q_min, arm.q_max - q).min()


def _navigation_commands(n: int, seed: int, x_max=0.08, z_max=0.10, tilt_max=0.4):
    """Commands over a navigation workspace, half of them on its edges and corners:
    x +-x_max, z +-z_max around L4 (m), yaw in [1.5, 3.5] rad, tilt +-tilt_max (rad)."""
    g = torch.Generator().manual_seed(seed)
    x = (torch.rand(n, generator=g) * 2 - 1) * x_max
    z = (torch.rand(n, generator=g) * 2 - 1) * z_max
    yaw = 1.5 + 2.0 * torch.rand(n, generator=g)
    tilt = (torch.rand(n, generator=g) * 2 - 1) * tilt_max
    h = n // 2
    x[:h] = torch.sign(x[:h]) * x_max
    z[: h // 2] = torch.sign(z[: h // 2]) * z_max
    tilt[:h] = torch.sign(tilt[:h]) * tilt_max
    yaw[: h // 4] = 1.5
    yaw[h // 4 : h // 2] = 3.5
    return x, z, yaw, tilt


# -------------------------------------------------------------------------- placement
def test_reference_placement_conversion():
    r_wh = reference_patient_rotation()
    # x_H -> +y_W, y_H (anterior) -> -z_W (the prone patient's back faces up), z_H -> -x_W.
    assert np.allclose(r_wh, [[0, 0, -1], [1, 0, 0], [0, -1, 0]], atol=1e-12)
    nav = reference_base_in_voxel_frame((0.0, -0.75, 0.5), (0.2, -0.45, 1.0))
    assert np.allclose(nav[:3, 3], [-0.30, 0.50, 0.20])
    assert np.allclose(nav[:3, 2], [0, -1, 0])  # base z = room up = -y_P
    drill = reference_base_in_voxel_frame((0.0, 0.5, 0.1), (0.2, -0.2, 0.7))
    assert np.allclose(drill[:3, 3], [0.70, 0.60, 0.20])
    for placement in (NAVIGATION_PROBE_BASE, SURGERY_PROBE_BASE, SURGERY_DRILL_BASE):
        assert np.allclose(placement.rotation(torch.float64).numpy(), nav[:3, :3])


def test_base_pose_follows_the_anchor():
    anchors = torch.tensor([[0.0, -0.1, 0.0], [0.01, -0.08, 0.02]])
    poses = NAVIGATION_PROBE_BASE.base_pose(anchors)
    assert poses.shape == (2, 4, 4)
    offset = torch.tensor(NAVIGATION_PROBE_BASE.offset)
    assert torch.allclose(poses[:, :3, 3], anchors + offset)
    assert NAVIGATION_PROBE_BASE.base_pose(anchors[0]).shape == (4, 4)
    with pytest.raises(ValueError, match="anchor"):
        NAVIGATION_PROBE_BASE.base_pose(torch.zeros(2, 2))
    with pytest.raises(ValueError, match="offset"):
        BasePlacement(offset=(0.0, float("nan"), 0.0), init_joints=(0.0,) * 7)


@pytest.mark.parametrize("back", ["curved_back", "flat_back"])
@pytest.mark.parametrize(
    ("x_max", "z_max", "tilt_max", "margin"),
    [
        (0.08, 0.10, 0.0, 0.2),  # navigation: beam along the normal, any yaw in [1.5, 3.5]
        (0.08, 0.10, 0.25, 0.05),
        (0.04, 0.05, 0.4, 0.05),  # reconstruction region around the vertebra
    ],
)
def test_navigation_workspace_is_reachable_with_margin(
    back, x_max, z_max, tilt_max, margin, request
):
    sc = _controller(request.getfixturevalue(back))
    n = 512
    commands = _navigation_commands(n, 0, x_max, z_max, tilt_max)
    result = sc.settle(sc.arm.default_joints(n), *commands, steps=120)
    assert bool(result.reached.all())
    assert bool(result.reachable.all())
    assert _joint_margin(sc.arm, result.q) >= margin  # rad, every joint of every pose


def test_tilted_workspace_edges_are_reached_or_reported(curved_back):
    """With 0.4 rad tilts at the x edges a few poses are out of reach from the default
    placement: each is then flagged unreachable (never left silently unreached), and the arm
    stops close by."""
    sc = _controller(curved_back)
    n = 512
    result = sc.settle(sc.arm.default_joints(n), *_navigation_commands(n, 1), steps=120)
    assert bool((result.reached | ~result.reachable).all())
    assert float(result.reached.float().mean()) > 0.9
    assert float(result.pos_error.max()) < 0.005


def test_overhead_placement_reaches_the_tilted_workspace(curved_back):
    sc = _controller(curved_back, OVERHEAD_PROBE_BASE)
    n = 512
    result = sc.settle(sc.arm.default_joints(n), *_navigation_commands(n, 0), steps=120)
    assert bool(result.reached.all())
    assert _joint_margin(sc.arm, result.q) >= 0.1


def test_surgery_probe_poses_are_reachable(curved_back):
    sc = _controller(curved_back, SURGERY_PROBE_BASE, model="franka_fr3")
    n = 256
    g = torch.Generator().manual_seed(1)
    x = -0.055 + 0.035 * torch.rand(n, generator=g)  # 20-55 mm left of the midline
    z = (torch.rand(n, generator=g) * 2 - 1) * 0.02
    yaw = 1.4 + 0.35 * torch.rand(n, generator=g)  # sagittal image plane
    tilt = -0.55 + 0.3 * torch.rand(n, generator=g)  # beam tilted toward the midline
    result = sc.settle(sc.arm.default_joints(n), x, z, yaw, tilt, steps=120)
    assert bool(result.reached.all())
    assert _joint_margin(sc.arm, result.q) >= 0.3


def test_surgery_drill_reaches_the_pedicle_corridor(curved_back):
    anchor = _anchor(curved_back)
    arm = Arm(
        ArmConfig(tool=DRILL_TOOL, init_joints=SURGERY_DRILL_BASE.init_joints),
        base_pose=SURGERY_DRILL_BASE.base_pose(anchor),
    )
    n = 256
    g = torch.Generator().manual_seed(2)

    def u(a, b):
        return a + (b - a) * torch.rand(n, generator=g)

    # Right-pedicle trajectories: 5-25 deg medial, +-10 deg cranio-caudal, target ~100 mm
    # below the skin; drill tip anywhere from 170 mm before the target down to it, within
    # 10 mm of the axis, drill axis within 0.15 rad of it.
    medial, cranial = torch.deg2rad(u(5, 25)), torch.deg2rad(u(-10, 10))
    axis = normalize(
        torch.stack(
            [
                -torch.sin(medial),
                torch.cos(medial) * torch.cos(cranial),
                torch.cos(medial) * torch.sin(cranial),
            ],
            -1,
        )
    )
    target = torch.stack([u(0.0, 0.015), anchor[1] + 0.1 + u(-0.02, 0.01), u(-0.01, 0.01)], -1)
    s = u(-0.17, 0.0)
    s[: n // 4] = -0.17
    s[n // 4 : n // 2] = 0.0
    side = normalize(torch.linalg.cross(axis, torch.randn(n, 3, generator=g)))
    tip = target + s[:, None] * axis + side * u(0, 0.01)[:, None]
    tilt_axis = normalize(torch.linalg.cross(axis, torch.randn(n, 3, generator=g)))
    z_d = (torch.linalg.matrix_exp(_skew(tilt_axis * u(0, 0.15)[:, None])) @ axis[..., None])[
        ..., 0
    ]
    x_d = normalize(torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]).expand(n, 3), z_d))
    rot = torch.stack([x_d, torch.linalg.cross(z_d, x_d), z_d], -1)
    roll = u(-0.5, 0.5)
    rot = rot @ torch.linalg.matrix_exp(_skew(torch.stack([0 * roll, 0 * roll, roll], -1)))
    result = arm.track(arm.default_joints(n), tip, rot, steps=120)
    assert bool(result.reached.all())
    assert _joint_margin(arm, result.q) >= 0.2


def _skew(v: torch.Tensor) -> torch.Tensor:
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2
    )


# --------------------------------------------------------------------- probe on the skin
@pytest.mark.parametrize("back", ["curved_back", "flat_back"])
def test_probe_face_stays_on_the_skin_along_a_sweep(back, request):
    """Lawn-mower sweeps over the workspace at 3 mm per control step (0.18 m/s) with the yaw
    drifting and a fixed tilt per arm: the reached probe face never leaves the skin by more
    than 1 mm, and the image is sliced within 1 mm of the command."""
    skin = request.getfixturevalue(back)
    sc = _controller(skin)
    n = 16
    tilt = torch.linspace(-0.3, 0.3, n)
    yaw0 = torch.linspace(1.6, 3.4, n)
    corners = []
    for i, row in enumerate((-0.09, -0.03, 0.03, 0.09)):
        corners += [(-0.08, row), (0.08, row)] if i % 2 == 0 else [(0.08, row), (-0.08, row)]
    path = []  # the polyline through the corners, resampled every 3 mm
    for (ax, az), (bx, bz) in zip(corners[:-1], corners[1:], strict=True):
        k = max(1, round(math.hypot(bx - ax, bz - az) / 0.003))
        path += [(ax + (bx - ax) * i / k, az + (bz - az) * i / k) for i in range(k)]
    x, z = torch.full((n,), path[0][0]), torch.full((n,), path[0][1])
    q = sc.settle(sc.arm.default_joints(n), x, z, yaw0, tilt).q
    for k, (px, pz) in enumerate(path[1:]):
        x = torch.full((n,), px)
        z = torch.full((n,), pz)
        yaw = yaw0 + 0.1 * math.sin(k / 10)
        step = sc.step(q, x, z, yaw, tilt)
        q = step.q
        assert float(sc.skin_distance(step.pos).abs().max()) <= 1e-3
        assert float(step.pos_error.max()) <= 1e-3
        assert bool(step.reachable.all())


def test_probe_stays_on_the_skin_at_the_largest_navigation_actions(curved_back):
    """Random navigation actions at their per-step maxima (6 mm in x and z, 0.2 rad of yaw):
    the arm cannot follow the yaw (A7 turns 0.04 rad per step), so it lags, but the probe face
    slides along the skin within 1 mm."""
    sc = _controller(curved_back)
    n = 32
    x, z, yaw, tilt = _navigation_commands(n, seed=3)
    x, z, tilt = x * 0.75, z * 0.75, tilt * 0.75
    q = sc.settle(sc.arm.default_joints(n), x, z, yaw, tilt).q
    g = torch.Generator().manual_seed(4)
    lagged = False
    for _ in range(100):
        a = torch.rand(n, 3, generator=g) * 2 - 1
        x = (x + 0.006 * a[:, 0]).clamp(-0.08, 0.08)
        z = (z + 0.006 * a[:, 1]).clamp(-0.1, 0.1)
        yaw = (yaw + 0.2 * a[:, 2]).clamp(1.5, 3.5)
        step = sc.step(q, x, z, yaw, tilt)
        q = step.q
        lagged |= bool((step.rot_error > 0.05).any())
        assert float(sc.skin_distance(step.pos).abs().max()) <= 1e-3
    assert lagged


def test_a_jump_lags_then_the_reached_pose_matches_the_command(curved_back):
    sc = _controller(curved_back)
    n = 8
    x0, z0 = torch.zeros(n), torch.zeros(n)
    yaw, tilt = torch.full((n,), 3.0), torch.zeros(n)
    q = sc.settle(sc.arm.default_joints(n), x0, z0, yaw, tilt).q
    x1, z1 = x0 + 0.06, z0 - 0.05  # 78 mm in one command
    step = sc.step(q, x1, z1, yaw, tilt)
    assert bool((step.pos_error > 0.01).all()) and bool(step.reachable.all())
    settled = sc.settle(step.q, x1, z1, yaw, tilt, steps=60)
    assert bool(settled.reached.all())
    mx, mz, myaw, mtilt = sc.skin.command_from_pose(settled.pos, settled.rot)
    assert torch.allclose(mx, x1, atol=1e-4) and torch.allclose(mz, z1, atol=1e-4)
    assert torch.allclose(myaw, yaw, atol=2e-3) and torch.allclose(mtilt, tilt, atol=2e-3)
    assert float(sc.skin_distance(settled.pos).abs().max()) <= 1e-4


def test_unreachable_commands_are_reported(curved_back):
    far = BasePlacement(offset=(-1.6, 0.44, 0.0), init_joints=NAVIGATION_PROBE_BASE.init_joints)
    sc = _controller(curved_back, far)
    n = 4
    zero = torch.zeros(n)
    result = sc.settle(sc.arm.default_joints(n), zero, zero, zero + 2.5, zero, steps=100)
    assert not bool(result.reachable.any())
    assert bool(torch.isfinite(result.pos).all()) and bool(torch.isfinite(result.q).all())


def test_bad_commands_raise(curved_back):
    sc = _controller(curved_back)
    q = sc.arm.default_joints(2)
    z = torch.zeros(2)
    with pytest.raises(ValueError, match="NaN"):
        sc.step(q, z * float("nan"), z, z, z)
    with pytest.raises(ValueError, match="equal"):
        sc.step(q, z, torch.zeros(3), z, z)
    with pytest.raises(ValueError, match="equal"):
        sc.step(q, torch.zeros(2, 1), z, z, z)
