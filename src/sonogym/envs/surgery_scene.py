"""The surgery scene: a Franka FR3 holding a 3-D probe still, a KUKA LBR Med 14 holding a drill.

Per env (env i -> patient i % P):

* the goal frame {G}: origin at the target point of the patient's planned pedicle trajectory
  (``Landmarks.trajectory(level, side)``), z_G along the trajectory from entry to target, x_G the
  vertebra's superior axis made orthogonal to z_G, y_G = z_G x x_G (x_G and y_G only fix the
  frame: the drill is symmetric about its axis, so nothing depends on them);
* the probe arm (FR3 + ``PROBE_TOOL``): placed once per reset on the skin ``probe_offset`` from
  the vertebra's midline on the side opposite the drilled pedicle, randomised per reset, image
  plane sagittal-ish (yaw pi/2: x_U along the spine) and tilted toward the midline, settled there
  by velocity-limited IK from the patient's nominal probe configuration, then held still;
* the drill arm (KUKA + ``DRILL_TOOL``): its tip {D} (z_D along the drill axis) tracks tip pose
  targets by velocity-limited IK; the scene solves once per patient a nominal configuration whose
  tip sits ``start_height`` above p_l on the trajectory's continuation with the drill axis along
  z_G, and each reset perturbs it by the paper's joint randomisation.

Arm bases are placed relative to the skin point above the target vertebra
(``sonogym.robots.placement``): the drill arm on the drilled side, the probe arm on the other.
For the left pedicle both placements are mirrored (base offset x -> -x, heading + pi).

The probe is still within an episode and the drill is not imaged, so the volume of an env is
sliced and simulated once per reset (``observe``) and reused by the env.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Literal, get_args

import numpy as np
import torch

from sonogym.envs.scene import ARM_TILT_MARGIN, ImagingReach, PatientScene
from sonogym.geometry import in_frame, matrix_from_axis_angle, normalize
from sonogym.ultrasound import ProbeGeometry

#: The drilled pedicle, the patient's side.
Side = Literal["right", "left"]
SIDES: tuple[str, ...] = get_args(Side)

#: Joint speed used only to *solve* the nominal configurations at construction (rad/s): the
#: solution is the same as with the real limits, found in fewer iterations.
_SOLVER_SPEED = 50.0


def swing_rotation(axis_from: torch.Tensor, axis_to: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) the smallest rotation turning unit vectors ``axis_from`` onto ``axis_to``
    (antiparallel: a half turn about an axis perpendicular to both)."""
    a, b = normalize(axis_from), normalize(axis_to)
    cross = torch.linalg.cross(a, b)
    s = cross.norm(dim=-1, keepdim=True)
    c = (a * b).sum(-1, keepdim=True)
    angle = torch.atan2(s, c)
    # Antiparallel fallback axis: any vector perpendicular to a.
    helper = torch.where(
        a[..., :1].abs() < 0.9,
        torch.tensor([1.0, 0.0, 0.0], dtype=a.dtype, device=a.device).expand_as(a),
        torch.tensor([0.0, 1.0, 0.0], dtype=a.dtype, device=a.device).expand_as(a),
    )
    perp = normalize(torch.linalg.cross(a, helper))
    axis = torch.where(s > 1e-9, cross / s.clamp_min(1e-12), perp)
    return matrix_from_axis_angle(axis * angle)


def mirrored(placement):
    """A base placement mirrored to the patient's other side: offset x -> -x, heading + pi."""
    ox, oy, oz = placement.offset
    return replace(placement, offset=(-ox, oy, oz), heading=placement.heading + math.pi)


class SurgeryScene(PatientScene):
    """Patients, goal frames, the probe arm, the drill arm and 3-D imaging for N envs.

    Args:
        cfg: the surgery config: ``PatientScene``'s fields (with "learned", the 2-D nets are
            applied slice by slice to the volume's elevation slices) and
            ``side``: "right" or "left", the drilled pedicle (the patient's side), of
            ``target_vertebra``;
            ``skin_distance``: l, distance (m) of p_l before the target along the trajectory;
            ``start_height``: m, nominal drill-tip start above p_l along the trajectory;
            ``probe_offset`` (+- ``probe_offset_noise``): m, probe distance from the
            vertebra's midline (opposite side);
            ``probe_tilt``: rad, image-plane tilt toward the midline;
            ``probe_yaw``: rad, yaw of the probe's lateral axis x_U (pi/2: along the spine);
            ``probe_settle_steps``: control steps of the probe arm's settle at a reset;
            ``gel_depth``: m, coupling gel under the probe face (overrides the ultrasound
            model's): tilted by ``probe_tilt``, the face's elevation edges stand off the
            skin (20 mm * sin 0.4 = 8 mm), and gel fills that wedge. None keeps its own;
            ``crop_to_reach``: images slice only what the still probe can image.
        num_envs: N.
        device: torch device of everything.
        render: build the slicer and simulator now (else on first ``observe``).
    """

    def __init__(self, cfg, num_envs: int, device: torch.device, render: bool = True) -> None:
        from sonogym.robots import SURGERY_DRILL_BASE, SURGERY_PROBE_BASE

        side, target_vertebra = cfg.side, cfg.target_vertebra
        probe_offset, probe_tilt, probe_yaw = cfg.probe_offset, cfg.probe_tilt, cfg.probe_yaw
        # the still probe: on the skin probe_offset (+ noise) from the midline, tilted
        # probe_tilt from the normal, plus the arm's settle
        reach = ImagingReach(probe_offset + cfg.probe_offset_noise, probe_tilt + ARM_TILT_MARGIN)
        super().__init__(
            cfg, num_envs, device, ProbeGeometry.volume_3d(), cfg.gel_depth,
            reach if cfg.crop_to_reach else None,
        )  # fmt: skip
        self.side = side
        self.skin_distance = float(cfg.skin_distance)
        self.start_height = float(cfg.start_height)
        self.probe_settle_steps = int(cfg.probe_settle_steps)

        # ---- per patient: goal frame, corridor radius, vertebra centre, skin anchor
        goal_pos, goal_rot, radius = [], [], []
        for p in self.patients:
            traj = p.landmarks.trajectory(target_vertebra, side)
            vert = p.landmarks.vertebra(target_vertebra)
            z = traj.direction
            x = vert.superior - (vert.superior @ z) * z
            x = x / np.linalg.norm(x)
            goal_pos.append(traj.target)
            goal_rot.append(np.stack([x, np.cross(z, x), z], 1))
            radius.append(traj.radius)
        f32 = dict(dtype=torch.float32, device=device)
        self._goal_pos_p = torch.tensor(np.array(goal_pos), **f32)  # (P, 3)
        self._goal_rot_p = torch.tensor(np.array(goal_rot), **f32)  # (P, 3, 3)
        self._radius_p = torch.tensor(radius, **f32)  # (P,)
        centres_p = self.target_centres_p
        pid = self.patient_index
        self.goal_pos = self._goal_pos_p[pid]  # (N, 3) origin of {G} in {P}
        self.goal_rot = self._goal_rot_p[pid]  # (N, 3, 3) axes of {G} in {P}
        self.radius = self._radius_p[pid]  # (N,) planned corridor radius r, m

        # ---- nominal probe surface command per patient: (x, z, yaw, tilt)
        probe_side = 1.0 if side == "left" else -1.0  # +1: patient's right (+x)
        # tilt rotates z_U toward -x_P for yaw pi/2 (see SkinSurface.surface_pose), so the
        # beam points toward the midline with tilt = probe_side * probe_tilt.
        # The mirrored probe arm (left pedicle) holds the probe turned by pi about the beam, as
        # the mirror image of the right-side pose: x_U then points inferior.
        if side == "left":
            probe_yaw = probe_yaw + math.pi
        yaw_sign = 1.0 if math.sin(probe_yaw) >= 0 else -1.0
        self._probe_cmd_p = torch.stack(
            [
                centres_p[:, 0] + probe_side * probe_offset,
                centres_p[:, 2],
                torch.full_like(centres_p[:, 0], probe_yaw),
                torch.full_like(centres_p[:, 0], probe_side * yaw_sign * probe_tilt),
            ],
            -1,
        )
        anchors_p = self.skin.point(
            centres_p[:, 0], centres_p[:, 2], torch.arange(len(self.patients), device=device)
        )
        drill_place = SURGERY_DRILL_BASE if side == "right" else mirrored(SURGERY_DRILL_BASE)
        probe_place = SURGERY_PROBE_BASE if side == "right" else mirrored(SURGERY_PROBE_BASE)
        self.drill_arm = self._arm("kuka_med14", "drill", drill_place, anchors_p[pid])
        self.probe_arm = self._arm("franka_fr3", "probe", probe_place, anchors_p[pid])
        self._solve_nominal(drill_place, probe_place, anchors_p)

        n = num_envs
        self.q_drill = self._q_drill_nominal_p[pid].clone()
        self.q_probe = self._q_probe_nominal_p[pid].clone()
        self.tip_pos, self.tip_rot = self.drill_arm.fk(self.q_drill)
        self.probe_pos, self.probe_rot = self.probe_arm.fk(self.q_probe)
        self.probe_cmd = self._probe_cmd_p[pid].float()  # (N, 4) commanded surface pose
        self.probe_reach_error = torch.zeros(n, **f32)  # m, settle residual
        if render:
            self.build_imaging()

    # ------------------------------------------------------------------ arms
    def _arm(self, model: str, tool: str, placement, anchors: torch.Tensor, solver=False):
        from sonogym.robots import DRILL_TOOL, PROBE_TOOL, Arm, ArmConfig

        cfg = ArmConfig(
            model=model,
            tool=DRILL_TOOL if tool == "drill" else PROBE_TOOL,
            init_joints=placement.init_joints,
            velocity_limits=(_SOLVER_SPEED,) * 7 if solver else None,
            ik_iterations=4 if solver else 2,
        )
        return Arm(cfg, base_pose=placement.base_pose(anchors.float()), device=self.device)

    def _solve_nominal(self, drill_place, probe_place, anchors_p: torch.Tensor) -> None:
        """Nominal joints per patient: drill tip ``start_height`` above p_l on the trajectory's
        continuation with its axis along z_G; probe at the centre of its randomisation range.
        Solved once by IK from the placements' initial joints."""
        n_p = len(self.patients)
        drill = self._arm("kuka_med14", "drill", drill_place, anchors_p, solver=True)
        q0 = drill.default_joints(n_p)
        _, rot0 = drill.fk(q0)
        z_g = self._goal_rot_p[:, :, 2]
        tgt_pos = self._goal_pos_p - (self.skin_distance + self.start_height) * z_g
        tgt_rot = swing_rotation(rot0[:, :, 2], z_g) @ rot0
        res = drill.track(q0, tgt_pos, tgt_rot, 40)
        self._check_solution(res, "drill", "start_height")
        self._q_drill_nominal_p = res.q

        probe = self._arm("franka_fr3", "probe", probe_place, anchors_p, solver=True)
        cmd = self._probe_cmd_p
        pos, rot = self.skin.surface_pose(
            cmd[:, 0], cmd[:, 1], cmd[:, 2], cmd[:, 3], torch.arange(n_p, device=self.device)
        )
        res = probe.track(probe.default_joints(n_p), pos.float(), rot.float(), 40)
        self._check_solution(res, "probe", "probe_offset/probe_tilt")
        self._q_probe_nominal_p = res.q

    def _check_solution(self, res, what: str, option: str) -> None:
        bad = (res.pos_error > 1e-3) | (res.rot_error > math.radians(1.0))
        if bool(bad.any()):
            names = [self.patients[i].name for i in torch.nonzero(bad).flatten().tolist()]
            raise ValueError(
                f"the {what} arm cannot reach its nominal pose for patient(s) {names} "
                f"(position error {res.pos_error.max().item() * 1e3:.1f} mm); change {option} "
                "or the target vertebra"
            )

    def reset_probe(self, env_ids: torch.Tensor, offset: torch.Tensor) -> None:
        """Place the probes of ``env_ids`` at their nominal surface command + ``offset`` (K, 2)
        = (dx, dz) m on the skin: the arm starts from the patient's nominal probe joints and
        settles by velocity-limited IK; the reached pose (FK) is stored."""
        pid = self.patient_index[env_ids]
        cmd = self._probe_cmd_p[pid].clone()
        cmd[:, :2] += offset.to(cmd)
        pos, rot = self.skin.surface_pose(cmd[:, 0], cmd[:, 1], cmd[:, 2], cmd[:, 3], pid)
        res = self.probe_arm.track(
            self._q_probe_nominal_p[pid],
            pos.float(),
            rot.float(),
            self.probe_settle_steps,
            env_ids=env_ids,
        )
        self.q_probe[env_ids] = res.q
        self.probe_pos[env_ids], self.probe_rot[env_ids] = res.pos, res.rot
        self.probe_cmd[env_ids] = cmd.float()
        self.probe_reach_error[env_ids] = res.pos_error

    def measured_probe_command(self, env_ids=slice(None)):
        """(x, z, yaw, tilt) of the reached probe poses."""
        return self.skin.command_from_pose(
            self.probe_pos[env_ids],
            self.probe_rot[env_ids],
            self.patient_index[env_ids],
        )

    # ------------------------------------------------------------------ drill
    def drill_start_joints(self, env_ids: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """Nominal drill joints of ``env_ids`` + ``noise`` (K, 7) rad, clamped into the limits."""
        q = self._q_drill_nominal_p[self.patient_index[env_ids]] + noise.to(self.q_drill)
        return self.drill_arm.clamp_joints(q)

    def drill_fk(self, env_ids: torch.Tensor, q: torch.Tensor):
        """Tip poses of joints ``q`` of the drill arms of ``env_ids``."""
        return self.drill_arm.fk(q, env_ids=env_ids)

    def set_drill(self, env_ids: torch.Tensor, q: torch.Tensor) -> None:
        self.q_drill[env_ids] = q
        self.tip_pos[env_ids], self.tip_rot[env_ids] = self.drill_fk(env_ids, q)

    def step_drill(self, target_pos: torch.Tensor, target_rot: torch.Tensor):
        """One control step of every drill arm toward tip targets in {P}; returns the
        ``IKResult`` (reached tip pose from FK, tracking errors)."""
        res = self.drill_arm.ik_step(self.q_drill, target_pos, target_rot)
        self.q_drill, self.tip_pos, self.tip_rot = res.q, res.pos, res.rot
        return res

    # ------------------------------------------------------------------ frames
    def tip_in_goal(self, env_ids=slice(None)) -> tuple[torch.Tensor, torch.Tensor]:
        """Drill tip in {G}: position (K, 3) m and rotation R_GD (K, 3, 3)."""
        return self._tip_in(self.goal_pos, self.goal_rot, env_ids)

    def tip_in_probe(self, env_ids=slice(None)) -> tuple[torch.Tensor, torch.Tensor]:
        """Drill tip in {U}: position (K, 3) m and rotation R_UD (K, 3, 3)."""
        return self._tip_in(self.probe_pos, self.probe_rot, env_ids)

    def _tip_in(self, frame_pos, frame_rot, ids) -> tuple[torch.Tensor, torch.Tensor]:
        return in_frame(frame_pos[ids], frame_rot[ids], self.tip_pos[ids], self.tip_rot[ids])
