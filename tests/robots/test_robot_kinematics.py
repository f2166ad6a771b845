"""URDF descriptions, forward kinematics against the published kinematic parameters, tools,
and Jacobians against finite differences."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from sonogym.geometry import axis_angle_from_matrix, make_pose, rot_x, rot_y, rot_z
from sonogym.robots import (
    DRILL_TOOL,
    PROBE_TOOL,
    URDF_DIR,
    Arm,
    ArmConfig,
    ToolConfig,
    arm_model,
    assemble_urdf,
)

F64 = torch.float64


# --------------------------------------------------------- hand-written kinematic parameters
def _rz(t: float) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]]
    return m


def _rx(t: float) -> np.ndarray:
    m = np.eye(4)
    m[1:3, 1:3] = [[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]]
    return m


def _tr(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = [x, y, z]
    return m


def kuka_dh(q: np.ndarray) -> np.ndarray:
    """KUKA LBR iiwa/Med 14 R820 flange pose, standard DH (d, a = 0, alpha)."""
    d = [0.36, 0.0, 0.42, 0.0, 0.40, 0.0, 0.126]
    alpha = [-math.pi / 2, math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, math.pi / 2, 0.0]
    m = np.eye(4)
    for i in range(7):
        m = m @ _rz(q[i]) @ _tr(0, 0, d[i]) @ _rx(alpha[i])
    return m


def franka_dh(q: np.ndarray) -> np.ndarray:
    """Franka FR3 flange pose, Franka's modified DH table (a_{i-1}, d_i, alpha_{i-1})."""
    table = [
        (0.0, 0.333, 0.0),
        (0.0, 0.0, -math.pi / 2),
        (0.0, 0.316, math.pi / 2),
        (0.0825, 0.0, math.pi / 2),
        (-0.0825, 0.384, -math.pi / 2),
        (0.0, 0.0, math.pi / 2),
        (0.088, 0.0, math.pi / 2),
    ]
    m = np.eye(4)
    for i, (a, d, alpha) in enumerate(table):
        m = m @ _rx(alpha) @ _tr(a, 0, 0) @ _rz(q[i]) @ _tr(0, 0, d)
    return m @ _tr(0, 0, 0.107)


DH = {"kuka_med14": kuka_dh, "franka_fr3": franka_dh}


def _arm(model: str = "kuka_med14", **kw) -> Arm:
    return Arm(ArmConfig(model=model, **kw), dtype=F64)


# ------------------------------------------------------------------------------ URDF
def test_urdf_limits_are_the_published_ones():
    kuka = Arm(ArmConfig(model="kuka_med14"), dtype=F64)
    deg = torch.tensor([170, 120, 170, 120, 170, 120, 175], dtype=F64)
    assert torch.allclose(kuka.q_max, torch.deg2rad(deg), atol=1e-6)
    assert torch.allclose(kuka.q_min, -torch.deg2rad(deg), atol=1e-6)
    speed = torch.tensor([85, 85, 100, 75, 130, 135, 135], dtype=F64)  # deg/s, Med 14 datasheet
    assert torch.allclose(kuka.velocity_limits, torch.deg2rad(speed), atol=1e-6)

    fr3 = Arm(ArmConfig(model="franka_fr3"), dtype=F64)
    q_max = [2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]
    q_min = [-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]
    assert torch.allclose(fr3.q_max, torch.tensor(q_max, dtype=F64), atol=1e-6)
    assert torch.allclose(fr3.q_min, torch.tensor(q_min, dtype=F64), atol=1e-6)
    assert fr3.velocity_limits.tolist() == pytest.approx([2.62] * 4 + [5.26, 4.18, 5.26])


def test_velocity_limit_override():
    arm = Arm(ArmConfig(velocity_limits=(2.175,) * 5 + (2.61,) * 2))
    assert arm.max_joint_step.tolist() == pytest.approx([2.175 / 60] * 5 + [2.61 / 60] * 2)
    with pytest.raises(ValueError, match="velocity_limits"):
        Arm(ArmConfig(velocity_limits=(1.0,) * 6))


def test_urdf_files_have_simple_visuals_and_no_meshes():
    for path in URDF_DIR.glob("*.urdf"):
        root = ET.parse(path).getroot()
        assert list(root.iter("visual")), path
        assert not list(root.iter("mesh")), f"{path.name} should use primitive shapes only"


# ------------------------------------------------------------------------ FK
def test_kuka_fk_at_hand_computed_configurations():
    arm = _arm()
    flange = "lbr_link_ee"
    q = torch.zeros(4, 7, dtype=F64)
    q[1, 1] = math.pi / 2  # A2 = 90 deg: the arm lies along +x
    q[2, 3] = math.pi / 2  # A4 = 90 deg about -y: the forearm points along -x
    q[3, 0] = math.pi / 2  # A1 = 90 deg with A2 = 90 deg: the arm lies along +y
    q[3, 1] = math.pi / 2
    pos, rot = arm.fk(q, link=flange)
    expected = torch.tensor(
        [
            [0.0, 0.0, 0.36 + 0.42 + 0.40 + 0.126],
            [0.42 + 0.40 + 0.126, 0.0, 0.36],
            [-(0.40 + 0.126), 0.0, 0.36 + 0.42],
            [0.0, 0.42 + 0.40 + 0.126, 0.36],
        ],
        dtype=F64,
    )
    assert torch.allclose(pos, expected, atol=1e-6)
    half = torch.tensor(math.pi / 2, dtype=F64)
    assert torch.allclose(rot[0], torch.eye(3, dtype=F64), atol=1e-6)
    assert torch.allclose(rot[1], rot_y(half), atol=1e-6)
    assert torch.allclose(rot[2], rot_y(-half), atol=1e-6)
    assert torch.allclose(rot[3], rot_z(half) @ rot_y(half), atol=1e-6)


def test_franka_fk_at_zero():
    arm = _arm("franka_fr3")
    pos, rot = arm.fk(torch.zeros(1, 7, dtype=F64), link="fr3_link8")
    # x: a4 + a5 + a7 = 0.0825 - 0.0825 + 0.088; z: d1 + d3 + d5 - d_flange.
    assert torch.allclose(
        pos[0], torch.tensor([0.088, 0.0, 0.333 + 0.316 + 0.384 - 0.107], dtype=F64), atol=1e-6
    )
    assert torch.allclose(rot[0], rot_x(torch.tensor(math.pi, dtype=F64)), atol=1e-6)


@pytest.mark.parametrize("model", ["kuka_med14", "franka_fr3"])
def test_fk_matches_the_published_dh_tables(model):
    arm = _arm(model)
    q = arm.random_joints(16, torch.Generator().manual_seed(0))
    pos, rot = arm.fk(q, link=arm.model.flange_link)
    for i in range(q.shape[0]):
        m = DH[model](q[i].numpy())
        assert np.abs(m[:3, 3] - pos[i].numpy()).max() < 1e-6
        assert np.abs(m[:3, :3] - rot[i].numpy()).max() < 1e-6


def test_base_pose_moves_everything():
    base = make_pose(rot_z(torch.tensor(0.7, dtype=F64)), torch.tensor([0.1, -0.2, 0.3], dtype=F64))
    local, world = _arm(), Arm(ArmConfig(), base_pose=base, dtype=F64)
    q = local.random_joints(8, torch.Generator().manual_seed(1))
    p0, r0 = local.fk(q)
    p1, r1 = world.fk(q)
    assert torch.allclose(
        p1, (base[:3, :3] @ p0.unsqueeze(-1)).squeeze(-1) + base[:3, 3], atol=1e-9
    )
    assert torch.allclose(r1, base[:3, :3] @ r0, atol=1e-9)


# ---------------------------------------------------------------------- tools
@pytest.mark.parametrize("model", ["kuka_med14", "franka_fr3"])
@pytest.mark.parametrize("tool", [PROBE_TOOL, DRILL_TOOL])
def test_tool_tip_is_the_configured_offset_from_the_flange(model, tool):
    arm = _arm(model, tool=tool)
    q = arm.random_joints(8, torch.Generator().manual_seed(2))
    pf, rf = arm.fk(q, link=arm.model.flange_link)
    pt, rt = arm.fk(q)
    offset = tool.tip_pose(F64)
    assert torch.allclose(pt, pf + (rf @ offset[:3, 3]), atol=1e-6)
    assert torch.allclose(rt, rf @ offset[:3, :3], atol=1e-6)


def test_tool_description_files_hold_the_default_offsets():
    for tool in (PROBE_TOOL, DRILL_TOOL):
        root = ET.parse(URDF_DIR / tool.urdf).getroot()
        joint = next(j for j in root.iter("joint") if j.get("name") == tool.tip_joint)
        xyz = [float(v) for v in joint.find("origin").get("xyz").split()]
        assert xyz == pytest.approx(list(tool.tip_pos))
    assert PROBE_TOOL.tip_pos == (0.0, 0.0, 0.13)  # reference: EE 0.13 m from the probe face
    assert DRILL_TOOL.tip_pos == (0.0, 0.0, 0.135)  # reference: drill tip 0.135 m from its EE


def test_custom_tool_rotation_reaches_the_kinematics():
    tool = ToolConfig(
        urdf="probe_tool.urdf",
        mount_link="probe_mount",
        tip_link="probe_face",
        tip_joint="probe_face_joint",
        tip_pos=(0.01, -0.02, 0.15),
        tip_rotvec=(0.0, 0.0, math.pi / 2),
    )
    arm = _arm(tool=tool)
    q = torch.zeros(1, 7, dtype=F64)
    pos, rot = arm.fk(q)
    assert torch.allclose(pos[0], torch.tensor([0.01, -0.02, 1.306 + 0.15], dtype=F64), atol=1e-6)
    assert torch.allclose(rot[0], rot_z(torch.tensor(math.pi / 2, dtype=F64)), atol=1e-6)
    assert "0.15" in assemble_urdf("kuka_med14", tool)


def test_unknown_names_raise_clear_errors():
    with pytest.raises(ValueError, match="known"):
        arm_model("ur5")
    with pytest.raises(ValueError, match="known"):
        ArmConfig(model="ur5")
    with pytest.raises(ValueError, match="unknown link"):
        _arm().fk(torch.zeros(1, 7, dtype=F64), link="nope")
    with pytest.raises(ValueError, match="tip_pos"):
        ToolConfig("probe_tool.urdf", "probe_mount", "probe_face", "probe_face_joint", (0, 0))


# --------------------------------------------------------------------- Jacobian
@pytest.mark.parametrize("model", ["kuka_med14", "franka_fr3"])
def test_jacobian_matches_finite_differences(model):
    base = make_pose(
        rot_x(torch.tensor(-1.2, dtype=F64)), torch.tensor([0.3, 0.1, -0.4], dtype=F64)
    )
    arm = Arm(ArmConfig(model=model), base_pose=base, dtype=F64)
    q = arm.random_joints(6, torch.Generator().manual_seed(3), margin=0.1)
    jac = arm.jacobian(q)
    h = 1e-6
    for j in range(7):
        dq = torch.zeros_like(q)
        dq[:, j] = h
        p_plus, r_plus = arm.fk(q + dq)
        p_minus, r_minus = arm.fk(q - dq)
        v = (p_plus - p_minus) / (2 * h)
        w = axis_angle_from_matrix(r_plus @ r_minus.transpose(-1, -2)) / (2 * h)
        assert torch.allclose(jac[:, :3, j], v, atol=1e-6), (model, j)
        assert torch.allclose(jac[:, 3:, j], w, atol=1e-6), (model, j)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_quat_from_matrix_inverts_matrix_from_quat_on_every_branch(dtype):
    # each of the four formulas (largest of w, x, y, z) and the 180-degree rotations
    from sonogym.geometry import matrix_from_quat, quat_from_matrix

    g = torch.Generator().manual_seed(0)
    q = torch.nn.functional.normalize(
        torch.randn(4000, 4, generator=g, dtype=torch.float64), dim=-1
    )
    axes = torch.eye(4, dtype=torch.float64)  # identity and 180 deg about x, y, z
    q = torch.cat([q, axes, torch.nn.functional.normalize(axes + 0.01, dim=-1)])
    q = torch.where(q[:, :1] < 0, -q, q)
    largest = q.abs().argmax(-1)
    assert set(largest.tolist()) == {0, 1, 2, 3}
    back = quat_from_matrix(matrix_from_quat(q).to(dtype)).double()
    assert (back[:, 0] >= 0).all()
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    # q and -q are one rotation; w = 0 leaves the sign to the formula
    err = torch.minimum((back - q).abs().amax(-1), (back + q).abs().amax(-1))
    assert err.max() < tol
    # batch dimensions pass through
    assert quat_from_matrix(matrix_from_quat(q[:12]).reshape(2, 6, 3, 3)).shape == (2, 6, 4)


# ------------------------------------------------------- specialised serial-chain kinematics
@pytest.mark.parametrize("model", ["kuka_med14", "franka_fr3"])
@pytest.mark.parametrize("tool", [PROBE_TOOL, DRILL_TOOL])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_serial_chain_kinematics_equal_pytorch_kinematics_bit_for_bit(model, tool, dtype):
    """The arms' FK and Jacobian come from ``SerialChainKinematics``; they must equal
    pytorch-kinematics' generic ones exactly, so trained runs reproduce across the switch."""
    arm = Arm(ArmConfig(model=model, tool=tool), dtype=dtype)
    q = arm.random_joints(3000, torch.Generator().manual_seed(11))
    generic = arm.chain.forward_kinematics_tensor(q)
    frames = arm.kinematics.frames(q)
    assert torch.equal(frames, generic)
    assert torch.equal(
        arm.kinematics.jacobian(frames), arm.chain.jacobian_tensor(q, all_transforms=generic)
    )


def _two_joint_urdf(second_joint_type: str) -> str:
    links = "".join(f'<link name="l{i}"/>' for i in range(3))
    joints = (
        '<joint name="j0" type="revolute"><parent link="l0"/><child link="l1"/>'
        '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
        f'<joint name="j1" type="{second_joint_type}"><parent link="l1"/><child link="l2"/>'
        '<origin xyz="0 0 0.1"/><axis xyz="1 0 0"/>'
        '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
    )
    return f'<robot name="r">{links}{joints}</robot>'


def test_serial_chain_kinematics_rejects_what_it_does_not_model():
    import pytorch_kinematics as pk

    from sonogym.robots.serial_chain import SerialChainKinematics

    revolute = pk.build_serial_chain_from_urdf(_two_joint_urdf("revolute"), "l2")
    q = torch.tensor([[0.3, -0.7]])
    assert torch.equal(
        SerialChainKinematics(revolute).frames(q), revolute.forward_kinematics_tensor(q)
    )
    prismatic = pk.build_serial_chain_from_urdf(_two_joint_urdf("prismatic"), "l2")
    with pytest.raises(ValueError, match="revolute and fixed joints"):
        SerialChainKinematics(prismatic)
