import math

import numpy as np
import torch

from sonogym.anatomy import SkinSurface


def test_height_is_bilinear_and_matches_the_first_body_voxel(small_phantom):
    p = small_phantom
    skin = p.skin
    z0 = float(p.landmarks.vertebra("L4").centre[2])
    x = torch.linspace(-0.08, 0.08, 1601, dtype=torch.float64)
    h = skin.height(x, torch.full_like(x, z0))
    assert (h[1:] - h[:-1]).abs().max() < 0.0005  # continuous: no voxel steps at 0.1 mm
    labels = p.labels.numpy()
    for xv in (-0.05, 0.0, 0.05):
        i, k = np.rint(p.world_to_voxel_np([xv, 0, z0])[[0, 2]]).astype(int)
        first = p.origin[1] + np.argmax(labels[i, :, k] > 0) * p.spacing[1]
        got = skin.height(torch.tensor(xv), torch.tensor(z0)).item()
        assert abs(got - first) <= p.spacing[1]


def test_normals_of_a_tilted_plane():
    x = np.arange(60) * 0.002 - 0.06
    height = -0.1 + 0.1 * x[:, None] + 0 * x[None, :]
    s = SkinSurface(height, -0.06, -0.06, 0.002, 0.002)
    n = s.normal(torch.tensor([0.0, 0.01]), torch.tensor([0.0, -0.01]))
    want = torch.tensor([-0.1, 1.0, 0.0]) / math.sqrt(1.01)
    assert torch.allclose(n, want.expand_as(n), atol=1e-5)
    assert torch.allclose(s.height(torch.tensor(0.013), torch.tensor(0.0)), torch.tensor(-0.0987))


def test_surface_pose_frame_and_its_inverse(small_phantom):
    skin = small_phantom.skin
    g = torch.Generator().manual_seed(0)
    n = 256
    x = (torch.rand(n, generator=g) - 0.5) * 0.12
    z = (torch.rand(n, generator=g) - 0.5) * 0.12
    yaw = torch.rand(n, generator=g) * 2 * math.pi
    tilt = (torch.rand(n, generator=g) - 0.5) * 0.8
    pos, rot = skin.surface_pose(x, z, yaw, tilt)
    eye = torch.eye(3).expand(n, 3, 3)
    assert torch.allclose(rot.transpose(1, 2) @ rot, eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(rot), torch.ones(n), atol=1e-5)
    assert torch.allclose(pos[:, 1], skin.height(x, z))  # face centre on the skin
    normal = skin.normal(x, z)
    xu, zu = rot[..., 0], rot[..., 2]
    assert (xu * normal).sum(-1).abs().max() < 1e-5  # lateral axis tangent to the skin
    ang = torch.atan2(xu[:, 2], xu[:, 0])
    assert (torch.remainder(ang - yaw + math.pi, 2 * math.pi) - math.pi).abs().max() < 1e-4
    cos_tilt = (zu * normal).sum(-1)
    assert torch.allclose(cos_tilt, torch.cos(tilt), atol=1e-5)
    x2, z2, yaw2, tilt2 = skin.command_from_pose(pos, rot)
    assert torch.allclose(x2, x) and torch.allclose(z2, z)
    assert (torch.remainder(yaw2 - yaw + math.pi, 2 * math.pi) - math.pi).abs().max() < 1e-4
    assert torch.allclose(tilt2, tilt, atol=1e-4)


def test_transverse_goal_pose_points_into_the_body(small_phantom):
    # yaw = pi: lateral axis toward the patient's left, beam anterior (+y).
    pos, rot = small_phantom.skin.surface_pose(
        torch.zeros(1), torch.zeros(1), torch.full((1,), math.pi)
    )
    assert rot[0, 1, 2] > 0.9  # z_U mostly +y
    assert rot[0, 0, 0] < -0.9  # x_U toward -x
    batched = small_phantom.skin.height(torch.zeros(3, 4), torch.zeros(3, 4))
    assert batched.shape == (3, 4)


def test_stacked_surfaces_answer_per_patient():
    x = np.arange(40) * 0.002 - 0.04
    flat = SkinSurface(np.full((40, 30), -0.1), -0.04, -0.03, 0.002, 0.002)
    sloped = SkinSurface(-0.08 + 0.1 * x[:, None] + 0 * x[None, :20], -0.04, -0.02, 0.002, 0.002)
    both = SkinSurface.stack([flat, sloped])
    assert both.num_patients == 2
    qx, qz = torch.tensor([0.01, 0.01, 0.0]), torch.tensor([0.0, 0.0, 0.0])
    pid = torch.tensor([0, 1, 1])
    h = both.height(qx, qz, pid)
    assert torch.allclose(h, torch.tensor([-0.1, -0.079, -0.08]), atol=1e-6)
    pos, rot = both.surface_pose(qx, qz, torch.full((3,), math.pi), patient=pid)
    assert torch.allclose(pos[:, 1], h)
    assert torch.allclose(rot[0, :, 2], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert rot[1, 0, 2] < -0.09  # sloped patient's normal leans toward -x
    assert both.z_range(1) == (-0.02, -0.02 + 0.002 * 19)


def test_aim_finds_the_skin_point_whose_normal_passes_through_the_target():
    """On a tilted plane y = tan(t) x the inward normal is n = (-sin t, cos t, 0) everywhere,
    so the beam reaching a target T at depth d starts at T - d n on the plane: known exactly."""
    t = 0.3
    xs = np.linspace(-0.1, 0.1, 101)
    zs = np.linspace(-0.1, 0.1, 101)
    h = np.tan(t) * xs[:, None] + 0 * zs[None, :]
    skin = SkinSurface(h, xs[0], zs[0], xs[1] - xs[0], zs[1] - zs[0], normal_sigma=0.004)
    target = torch.tensor([[0.01, 0.08, -0.02], [-0.02, 0.05, 0.03]], dtype=torch.float64)
    x, z = skin.aim(target)
    assert skin.beam_miss(x, z, target).max() < 1e-5
    n = torch.tensor([-math.sin(t), math.cos(t), 0.0], dtype=torch.float64)
    # the skin point s = T - d n lies on the plane: (T_y - d cos t) = tan t (T_x + d sin t)
    d = (target[:, 1] - math.tan(t) * target[:, 0]) / (math.cos(t) + math.tan(t) * math.sin(t))
    expect = target - d[:, None] * n
    assert torch.allclose(x, expect[:, 0], atol=1e-5) and torch.allclose(z, expect[:, 2], atol=1e-5)
