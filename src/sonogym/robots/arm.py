"""Batched kinematic arms: forward kinematics, Jacobians, damped-least-squares IK.

The paper drives a KUKA LBR Med 14 and a Franka arm with IsaacLab's differential IK and PD
joint control. Without a physics engine the arms here are kinematic: what matters is which
poses they reach, that joint limits hold, and that tracking lags behind a command that moves
faster than the joints allow. The image is then sliced from the pose the arm actually reached.

Frames: every pose an ``Arm`` takes or returns is in the patient frame {P} (metres); the arm's
base pose in {P} is given at construction (see ``sonogym.robots.placement``). Kinematics are
computed in the base frame, on pytorch-kinematics' parsed chain by ``SerialChainKinematics``
(same results, fewer ops), and mapped to {P}.

One control step (``Arm.ik_step``) stands in for the reference's DLS step + PD tracking at
60 Hz: ``ArmConfig.ik_iterations`` weighted damped-least-squares iterations

    dq = (W J)^T ((W J)(W J)^T + lambda^2 I)^-1 W e,   e = (p_target - p, rotvec(R_target R^T)),
    W = diag(1, 1, 1, w, w, w),  w = ``rotation_weight`` (m/rad),

in which joints pressed against a position limit are removed from the least-squares problem
(so the free joints take over), and the update is then scaled down uniformly so that no joint
leaves the box it can reach in one step, [q0 - v dt, q0 + v dt]. Joint position limits and
per-step velocity limits therefore hold exactly; a command faster than the joints allow is
followed along the same joint-space direction, more slowly (the probe slides along the skin
instead of leaving it), and leaves a tracking error that closes over the following steps.
With w < 1 a step that cannot do everything favours position over orientation.

Reachability of a target, reported per arm after every step:

* ``reached``: position error <= ``position_tolerance`` and rotation error <=
  ``rotation_tolerance``;
* ``unreachable``: not reached, and either the tip target lies beyond the arm's reach (farther
  from the shoulder than the sum of the link lengths from there to the tip), or the step
  stalled: the step was not slowed by the joint speed limits and yet the weighted error
  ``|e_p| + rotation_weight * |e_r|`` fell by less than ``stall_ratio`` of its value, i.e. the
  arm is pinned at joint limits, stretched at a singularity, or stuck in a local minimum from
  which this target cannot be reached. A target that is merely far away (the arm moving at its
  speed limits) is neither reached nor unreachable.

Nothing here produces NaN for finite inputs: the damped system is solved in float64 and any
non-finite update is replaced by zero. NaN/inf targets or joints raise ``ValueError``.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import pytorch_kinematics as pk
import torch

from sonogym.checks import expect_all
from sonogym.geometry import axis_angle_from_matrix, invert_pose
from sonogym.robots.description import arm_model, assemble_urdf
from sonogym.robots.serial_chain import SerialChainKinematics
from sonogym.robots.tools import PROBE_TOOL, ToolConfig

#: Joint speed limits of the reference implementation's IsaacLab actuators (rad/s): 2.175 for
#: joints 1-5 and 2.61 for joints 6-7, for both arms (they are the Franka Panda's published
#: limits). Pass as ``ArmConfig.velocity_limits`` to mimic the reference instead of the
#: manufacturers' limits written in the URDF files.
REFERENCE_VELOCITY_LIMITS: tuple[float, ...] = (2.175,) * 5 + (2.61,) * 2


@dataclass(frozen=True)
class ArmConfig:
    """Arm model, tool, joint limits and differential-IK settings."""

    model: str = "kuka_med14"  # arm description: "kuka_med14" or "franka_fr3"
    tool: ToolConfig = PROBE_TOOL  # flange-mounted tool; its tip is the controlled frame
    init_joints: tuple[float, ...] | None = None  # rad; None: the model's default configuration
    velocity_limits: tuple[float, ...] | None = None  # rad/s per joint; None: the URDF's limits
    control_dt: float = 1.0 / 60.0  # s per control step (reference: 2 physics steps at 120 Hz)
    ik_damping: float = 0.01  # DLS damping lambda (m and rad; reference 0.1 / 1e-5 / 0.01)
    ik_iterations: int = 2  # DLS iterations per control step (reference: one per physics step)
    position_tolerance: float = 1e-4  # m; a target is reached below this position error
    rotation_tolerance: float = math.radians(0.1)  # rad; ... and below this rotation error
    stall_ratio: float = 0.01  # relative error decrease per step below which a step stalled
    rotation_weight: float = 0.1  # m per rad: weight of rotation vs position errors in IK

    def __post_init__(self) -> None:
        arm_model(self.model)  # raises on unknown names
        for name in ("control_dt", "ik_damping", "position_tolerance", "rotation_tolerance"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ArmConfig.{name} must be a finite number > 0, got {v!r}")
        if not (isinstance(self.ik_iterations, int) and self.ik_iterations >= 1):
            raise ValueError(f"ArmConfig.ik_iterations must be an int >= 1: {self.ik_iterations}")
        if not 0 <= self.stall_ratio < 1:
            raise ValueError(f"ArmConfig.stall_ratio must be in [0, 1), got {self.stall_ratio}")
        if not (math.isfinite(self.rotation_weight) and self.rotation_weight > 0):
            raise ValueError(f"ArmConfig.rotation_weight must be > 0, got {self.rotation_weight}")
        if self.velocity_limits is not None and not all(
            math.isfinite(v) and v > 0 for v in self.velocity_limits
        ):
            raise ValueError(f"ArmConfig.velocity_limits must be > 0, got {self.velocity_limits}")


@dataclass
class IKResult:
    """Outcome of one or more control steps for N arms (all tensors batch-first).

    Attributes:
        q: (N, 7) joint positions after the step(s), rad.
        pos: (N, 3) reached tip position in {P}, m.
        rot: (N, 3, 3) reached tip orientation in {P} (columns: the tip frame's axes).
        pos_error: (N,) distance from the target position, m.
        rot_error: (N,) angle from the target orientation, rad.
        reached: (N,) bool, both errors within the config's tolerances.
        unreachable: (N,) bool, see the module docstring.
    """

    q: torch.Tensor
    pos: torch.Tensor
    rot: torch.Tensor
    pos_error: torch.Tensor
    rot_error: torch.Tensor
    reached: torch.Tensor
    unreachable: torch.Tensor

    @property
    def reachable(self) -> torch.Tensor:
        """(N,) bool, not ``unreachable``."""
        return ~self.unreachable


def _check_finite(name: str, t: torch.Tensor) -> None:
    expect_all(torch.isfinite(t), f"{name} contains NaN or inf; pass finite values")


class Arm:
    """A batch of identical 7-DoF arms with a tool, kinematic (see the module docstring).

    Args:
        config: arm model, tool and IK settings.
        base_pose: (4, 4) or (N, 4, 4) pose of the arm's base frame in {P} (metres); the
            identity if None. One pose serves all arms; N poses give each arm its own.
        device, dtype: where and in which precision the kinematics run.

    Stateless: joint positions are passed in and returned, so an environment owns them.
    """

    def __init__(
        self,
        config: ArmConfig | None = None,
        base_pose: torch.Tensor | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.config = config = config if config is not None else ArmConfig()
        self.model = arm_model(config.model)
        self.device = torch.device(device)
        self.dtype = dtype
        urdf = assemble_urdf(config.model, config.tool)
        chain = pk.build_serial_chain_from_urdf(urdf, config.tool.tip_link)
        self.chain = chain.to(dtype=dtype, device=self.device)
        self.kinematics = SerialChainKinematics(self.chain)
        self.joint_names: list[str] = self.chain.get_joint_parameter_names()
        n = len(self.joint_names)
        lo, hi = self.chain.get_joint_limits()
        self.q_min = torch.tensor(lo, dtype=dtype, device=self.device)
        self.q_max = torch.tensor(hi, dtype=dtype, device=self.device)
        if config.velocity_limits is None:
            v = self.chain.get_joint_velocity_limits()[1]
        else:
            v = config.velocity_limits
        if len(v) != n:
            raise ValueError(f"velocity_limits needs {n} values for {config.model}, got {len(v)}")
        self.velocity_limits = torch.tensor(v, dtype=dtype, device=self.device)
        init = config.init_joints if config.init_joints is not None else self.model.default_joints
        if len(init) != n:
            raise ValueError(f"init_joints needs {n} values for {config.model}, got {len(init)}")
        self.init_joints = torch.tensor(init, dtype=dtype, device=self.device)
        if bool(((self.init_joints < self.q_min) | (self.init_joints > self.q_max)).any()):
            raise ValueError(f"init_joints {init} outside the joint limits of {config.model}")

        # Frame indices: the tip is the chain's last frame.
        self._frame_index = dict(self.chain.frame_to_idx)
        self._tip_index = self._frame_index[config.tool.tip_link]
        # Reach bound: sum of segment lengths from joint 2 (on joint 1's axis, so fixed in the
        # base frame) through the following joint origins to the tip, at the zero configuration.
        joints = ET.fromstring(urdf).iter("joint")
        child = {j.get("name"): j.find("child").get("link") for j in joints}
        moving = [child[name] for name in self.joint_names]
        zero = self.chain.forward_kinematics(
            torch.zeros(1, n, dtype=dtype, device=self.device), end_only=False
        )
        poses = [zero[name].get_matrix()[0].double() for name in moving]
        poses.append(zero[config.tool.tip_link].get_matrix()[0].double())
        pts = torch.stack([p[:3, 3] for p in poses])
        axis1 = poses[0][:3, :3] @ torch.tensor(
            self.chain.find_joint(self.joint_names[0]).axis.tolist(),
            dtype=torch.float64,
            device=self.device,
        )
        rel = pts[1] - pts[0]
        start = 1 if (rel - (rel @ axis1) * axis1).norm() < 1e-6 else 0
        self._shoulder = pts[start].to(dtype)
        self.reach = float((pts[start + 1 :] - pts[start:-1]).norm(dim=-1).sum())

        w = config.rotation_weight
        self._task_weight = torch.tensor([1.0, 1.0, 1.0, w, w, w], dtype=torch.float64).to(
            self.device
        )
        self._damping_eye = config.ik_damping**2 * torch.eye(
            6, dtype=torch.float64, device=self.device
        )
        self._base = torch.eye(4, dtype=dtype, device=self.device)
        self._base_inv = self._base.clone()
        # (joints, their version counter, all frames' FK) of the last ik_step's result
        self._last_frames: tuple[torch.Tensor, int, torch.Tensor] | None = None
        if base_pose is not None:
            self.set_base_pose(base_pose)

    # ----------------------------------------------------------------- properties
    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def base_pose(self) -> torch.Tensor:
        """(4, 4) or (N, 4, 4) base pose in {P}."""
        return self._base

    @property
    def max_joint_step(self) -> torch.Tensor:
        """(7,) largest joint motion in one control step, rad (velocity limit * control_dt)."""
        return self.velocity_limits * self.config.control_dt

    @property
    def link_names(self) -> list[str]:
        """Names of the frames ``fk`` can report."""
        return list(self._frame_index)

    def set_base_pose(self, pose: torch.Tensor) -> None:
        """Set the base pose(s) in {P}: (4, 4) for all arms or (N, 4, 4) one per arm."""
        pose = torch.as_tensor(pose).to(self.device, self.dtype)
        if pose.shape[-2:] != (4, 4) or pose.dim() not in (2, 3):
            raise ValueError(f"base_pose must be (4, 4) or (N, 4, 4), got {tuple(pose.shape)}")
        _check_finite("base_pose", pose)
        rot = pose[..., :3, :3]
        eye = torch.eye(3, dtype=self.dtype, device=self.device)
        if not torch.allclose(rot @ rot.transpose(-1, -2), eye.expand_as(rot), atol=1e-4):
            raise ValueError("base_pose rotation is not orthonormal")
        self._base = pose
        self._base_inv = invert_pose(pose)

    # ------------------------------------------------------------------ joints
    def default_joints(self, n: int) -> torch.Tensor:
        """(n, 7) copies of the configured initial joints, rad."""
        return self.init_joints.expand(n, -1).clone()

    def clamp_joints(self, q: torch.Tensor) -> torch.Tensor:
        """Clamp (N, 7) joints into the position limits."""
        return torch.maximum(torch.minimum(q, self.q_max), self.q_min)

    def random_joints(
        self, n: int, generator: torch.Generator | None = None, margin: float = 0.0
    ) -> torch.Tensor:
        """(n, 7) joints uniform within [q_min + margin, q_max - margin], rad."""
        lo, hi = self.q_min + margin, self.q_max - margin
        if bool((hi <= lo).any()):
            raise ValueError(f"margin {margin} rad leaves no room inside the joint limits")
        u = torch.rand(n, self.num_joints, generator=generator, dtype=torch.float64)
        return (lo + u.to(self.device, self.dtype) * (hi - lo)).contiguous()

    def _bases(self, env_ids: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Base poses and their inverses of the arms ``env_ids`` (None: all)."""
        if env_ids is None or self._base.dim() == 2:
            return self._base, self._base_inv
        return self._base[env_ids], self._base_inv[env_ids]

    def _check_q(
        self, q: torch.Tensor, within_limits: bool = False, env_ids: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Validate (N, 7) joints (of the arms ``env_ids`` when given); with ``within_limits``,
        reject joints more than 1e-4 rad outside the limits and clamp smaller excursions
        (rounding) into them."""
        if q.dim() != 2 or q.shape[1] != self.num_joints:
            raise ValueError(f"joints must be (N, {self.num_joints}), got {tuple(q.shape)}")
        base, _ = self._bases(env_ids)
        if base.dim() == 3 and base.shape[0] not in (1, q.shape[0]):
            what = "arms selected by env_ids" if env_ids is not None else "base poses"
            raise ValueError(
                f"{q.shape[0]} joint vectors for {base.shape[0]} {what}; pass one "
                "base pose per arm or a single (4, 4) pose"
            )
        _check_finite("joint positions", q)
        q = q.to(self.device, self.dtype)
        if within_limits:
            tol = 1e-4
            expect_all(
                (q >= self.q_min - tol) & (q <= self.q_max + tol),
                "joint positions outside the joint limits; start from Arm.default_joints, "
                "Arm.random_joints or Arm.clamp_joints",
            )
            q = self.clamp_joints(q)
        return q

    # -------------------------------------------------------------- kinematics
    def _kin_base(
        self, q: torch.Tensor, frames: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Tip pose and Jacobian in the base frame: pos (N,3), rot (N,3,3), J (N,6,7).
        ``frames``: every frame's FK at ``q`` when already known."""
        if frames is None:
            frames = self.kinematics.frames(q)
        jac = self.kinematics.jacobian(frames)
        tip = frames[self._tip_index]
        return tip[:, :3, 3], tip[:, :3, :3], jac

    @staticmethod
    def _apply(pose: torch.Tensor, pos: torch.Tensor, rot: torch.Tensor):
        """Rigid transform ``pose`` ((4, 4) or (N, 4, 4)) applied to positions and rotations."""
        r, t = pose[..., :3, :3], pose[..., :3, 3]
        return (r @ pos.unsqueeze(-1)).squeeze(-1) + t, r @ rot

    def fk(
        self, q: torch.Tensor, link: str | None = None, env_ids: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Pose in {P} of the tool tip (or of ``link``): pos (N, 3) m, rot (N, 3, 3).
        ``env_ids``: the arms (rows of the base poses) ``q`` belongs to; None: all."""
        q = self._check_q(q, env_ids=env_ids)
        if link is None:
            index = self._tip_index
        elif link in self._frame_index:
            index = self._frame_index[link]
        else:
            raise ValueError(f"unknown link {link!r}; known: {self.link_names}")
        pose = self.kinematics.frames(q)[index]
        return self._apply(self._bases(env_ids)[0], pose[:, :3, 3], pose[:, :3, :3])

    def jacobian(self, q: torch.Tensor) -> torch.Tensor:
        """(N, 6, 7) geometric Jacobian of the tip in {P}: rows (linear velocity of the tip
        origin, angular velocity), both expressed in {P}, per joint velocity (rad/s)."""
        q = self._check_q(q)
        _, _, jac = self._kin_base(q)
        r = self._base[..., :3, :3]
        return torch.cat([r @ jac[:, :3], r @ jac[:, 3:]], dim=1)

    @staticmethod
    def pose_error(
        pos: torch.Tensor, rot: torch.Tensor, target_pos: torch.Tensor, target_rot: torch.Tensor
    ) -> torch.Tensor:
        """(N, 6) error (target_pos - pos, rotation vector of target_rot @ rot^T), m and rad."""
        e_rot = axis_angle_from_matrix(target_rot @ rot.transpose(-1, -2))
        return torch.cat([target_pos - pos, e_rot], dim=-1)

    def _dls(self, jac: torch.Tensor, err: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
        """Weighted damped least squares over the free joints: (N, 7) joint update."""
        w = self._task_weight
        jw = (jac.double() * w[:, None]) * free.double().unsqueeze(1)
        a = jw @ jw.transpose(1, 2) + self._damping_eye
        x, _ = torch.linalg.solve_ex(a, (err.double() * w).unsqueeze(-1))
        dq = (jw.transpose(1, 2) @ x).squeeze(-1).to(self.dtype)
        return torch.nan_to_num(dq, nan=0.0, posinf=0.0, neginf=0.0)

    # ---------------------------------------------------------------------- IK
    def ik_step(
        self,
        q: torch.Tensor,
        target_pos: torch.Tensor,
        target_rot: torch.Tensor,
        env_ids: torch.Tensor | None = None,
    ) -> IKResult:
        """One control step toward tip targets in {P}.

        Args:
            q: (N, 7) current joints, rad (within limits).
            target_pos: (N, 3) tip position targets in {P}, m.
            target_rot: (N, 3, 3) tip orientation targets in {P}.
            env_ids: the arms (rows of the base poses) the N rows belong to; None: all arms.
        """
        # the frames of the joints this method returned last time, if ``q`` is them unchanged
        cached = self._last_frames
        frames = cached[2] if cached and cached[0] is q and cached[1] == q._version else None
        q = self._check_q(q, within_limits=True, env_ids=env_ids)
        base, base_inv = self._bases(env_ids)
        n = q.shape[0]
        if target_pos.shape != (n, 3) or target_rot.shape != (n, 3, 3):
            raise ValueError(
                f"targets must be (N, 3) and (N, 3, 3) with N = {n}, got "
                f"{tuple(target_pos.shape)} and {tuple(target_rot.shape)}"
            )
        _check_finite("target_pos", target_pos)
        _check_finite("target_rot", target_rot)
        tp, tr = self._apply(
            base_inv, target_pos.to(self.device, self.dtype), target_rot.to(self.device, self.dtype)
        )
        step = self.max_joint_step
        lo = torch.maximum(self.q_min, q - step)
        hi = torch.minimum(self.q_max, q + step)
        slack = 1e-6  # rad
        err0 = None
        limited = torch.zeros(q.shape[0], dtype=torch.bool, device=q.device)
        for _ in range(self.config.ik_iterations):
            pos, rot, jac = self._kin_base(q, frames)
            frames = None
            err = self.pose_error(pos, rot, tp, tr)
            if err0 is None:
                err0 = err
            dq = self._dls(jac, err, torch.ones_like(q))
            pinned = ((q <= self.q_min + slack) & (dq < 0)) | ((q >= self.q_max - slack) & (dq > 0))
            # Re-solve without the pinned joints (skipped on CPU when none is; on CUDA always,
            # to avoid a host sync).
            if q.device.type != "cpu" or bool(pinned.any()):
                dq = self._dls(jac, err, (~pinned).to(q.dtype))
            room = torch.where(dq > 0, hi - q, q - lo).clamp_min(0)
            ratio = torch.where(dq != 0, room / dq.abs().clamp_min(1e-30), torch.inf)
            scale = ratio.amin(-1, keepdim=True).clamp(max=1)
            limited |= scale[:, 0] < 1.0
            q = torch.maximum(torch.minimum(q + dq * scale, hi), lo)
        frames = self.kinematics.frames(q)
        # Kept for the next call: a control loop passes ``result.q`` straight back, and its
        # first iteration needs these frames (one FK of three saved; the joints are within
        # limits, so the next call's clamp leaves them bit-identical).
        self._last_frames = (q, q._version, frames)
        tip = frames[self._tip_index]
        pos, rot = tip[:, :3, 3], tip[:, :3, :3]
        err = self.pose_error(pos, rot, tp, tr)
        return self._result(base, q, pos, rot, err, err0, tp, limited)

    def _result(
        self,
        base: torch.Tensor,
        q: torch.Tensor,
        pos: torch.Tensor,
        rot: torch.Tensor,
        err: torch.Tensor,
        err0: torch.Tensor,
        target_pos_base: torch.Tensor,
        limited: torch.Tensor,
    ) -> IKResult:
        cfg = self.config
        pos_err = err[:, :3].norm(dim=-1)
        rot_err = err[:, 3:].norm(dim=-1)
        reached = (pos_err <= cfg.position_tolerance) & (rot_err <= cfg.rotation_tolerance)
        w1 = pos_err + cfg.rotation_weight * rot_err
        w0 = err0[:, :3].norm(dim=-1) + cfg.rotation_weight * err0[:, 3:].norm(dim=-1)
        stalled = (w1 > (1.0 - cfg.stall_ratio) * w0) & ~limited
        beyond = (target_pos_base - self._shoulder).norm(dim=-1) > self.reach
        unreachable = ~reached & (stalled | beyond)
        return IKResult(q, *self._apply(base, pos, rot), pos_err, rot_err, reached, unreachable)

    def track(
        self,
        q: torch.Tensor,
        target_pos: torch.Tensor,
        target_rot: torch.Tensor,
        steps: int,
        env_ids: torch.Tensor | None = None,
    ) -> IKResult:
        """``steps`` control steps toward fixed targets (e.g. to settle the arm at a reset);
        returns the last step's result. ``env_ids`` as in ``ik_step``."""
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        result = self.ik_step(q, target_pos, target_rot, env_ids)
        for _ in range(steps - 1):
            result = self.ik_step(result.q, target_pos, target_rot, env_ids)
        return result
