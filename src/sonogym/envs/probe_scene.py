"""A probe held on the back of each env's patient by a robot arm, and its images.

Shared by the navigation and reconstruction tasks: ``PatientScene`` (patients, skins, imaging)
plus the arm that tracks surface commands (or an ideal probe when ``robot=None``); images are
sliced from the pose the arm actually reached.
"""

from __future__ import annotations

import operator

import torch

from sonogym.envs.scene import ARM_TILT_MARGIN, ImagingReach, PatientScene
from sonogym.geometry import wrap_angle
from sonogym.ultrasound import ProbeGeometry

#: rad: the commanded yaw is held within this of the yaw the arm reached (anti-windup).
MAX_YAW_LEAD = 0.5


class ProbeScene(PatientScene):
    """Probe arm + patients + imaging for N envs.

    Args:
        cfg: a probe task's config: ``PatientScene``'s fields plus ``robot`` (arm model name,
            "kuka_med14" or "franka_fr3", or None for an ideal probe), ``crop_to_reach`` and
            ``workspace_half_extent`` (with ``crop_to_reach``, images slice only what a probe
            within ``workspace_half_extent`` of the target, tilted up to ``tilt_limit`` (when
            the task has one) + ``ARM_TILT_MARGIN``, can image).
        num_envs, device, keep_volumes: see ``PatientScene``.
        render: build the slicer and simulator now (else on first ``observe``).
        probe: the imaging geometry (default: the paper's 2-D linear probe).
        aimed: the workspace square is centred on the skin point whose beam passes through
            the target's centre (navigation's goal) instead of the point above it.
    """

    def __init__(
        self,
        cfg,
        num_envs: int,
        device: torch.device,
        render: bool = True,
        keep_volumes: bool = True,
        probe: ProbeGeometry | None = None,
        aimed: bool = False,
    ) -> None:
        reach = None
        if cfg.crop_to_reach:
            tilt = getattr(cfg, "tilt_limit", 0.0) + ARM_TILT_MARGIN
            reach = ImagingReach(cfg.workspace_half_extent, tilt, aimed)
        probe = probe or ProbeGeometry.linear_2d()
        super().__init__(cfg, num_envs, device, probe, reach=reach, keep_volumes=keep_volumes)
        self.robot = robot = cfg.robot
        self.reachable = torch.ones(num_envs, dtype=torch.bool, device=device)
        self._cmd = torch.zeros(num_envs, 4, device=device)  # last command (x, z, yaw, tilt)
        self._measured = None  # ((probe_pos, probe_rot), their versions, measured command)
        if robot is not None:
            self._init_robot(robot)
        if render:
            self.build_imaging()

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of the 2-D image."""
        return self.probe_geometry.shape[1:]

    # ------------------------------------------------------------------ robot
    def _init_robot(self, model: str) -> None:
        from sonogym.robots import Arm, ArmConfig, SurfaceController
        from sonogym.robots.placement import NAVIGATION_PROBE_BASE

        c = self.target_centres.double()
        anchor = self.skin.point(c[:, 0], c[:, 2], self.patient_index)
        base = NAVIGATION_PROBE_BASE.base_pose(anchor)
        cfg = ArmConfig(model=model, init_joints=NAVIGATION_PROBE_BASE.init_joints)
        self.arm = Arm(cfg, base_pose=base, device=self.device)
        self.controller = SurfaceController(self.skin, self.arm)
        self.q = self.arm.default_joints(self.num_envs)

    def surface_pose(self, cmd: torch.Tensor, env_ids=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Commands (K, 3 or 4) = (x, z, yaw[, tilt]) -> probe poses on the envs' patients."""
        pid = self.patient_index if env_ids is None else self.patient_index[env_ids]
        tilt = cmd[:, 3] if cmd.shape[1] > 3 else None
        pos, rot = self.skin.surface_pose(cmd[:, 0], cmd[:, 1], cmd[:, 2], tilt, patient=pid)
        return pos.float(), rot.float()

    def reset(self, env_ids: torch.Tensor, cmd: torch.Tensor) -> None:
        """Place the probes of ``env_ids`` at commands ``cmd``: the arm starts from its default
        joints and settles onto the pose (the reference's settle phase); the other envs' arms
        are not touched. Their contact force starts again at the config's."""
        self.reset_force(env_ids)
        if self.robot is None:
            pos, rot = self.surface_pose(cmd, env_ids)
            self.probe_pos[env_ids], self.probe_rot[env_ids] = pos, rot
            self.reachable[env_ids] = True
            return
        self._cmd[env_ids, : cmd.shape[1]] = cmd
        res = self.controller.settle(
            self.arm.default_joints(len(env_ids)),
            *self._cmd_args(self._cmd[env_ids]),
            patient=self.patient_index[env_ids],
            env_ids=env_ids,
        )
        self._store(env_ids, res)

    def step(self, cmd: torch.Tensor) -> None:
        """One control step of every arm toward its command.

        With an arm, ``cmd``'s yaw is first pulled (in place) to within ``MAX_YAW_LEAD`` of the
        reached yaw. Without this, an arm held back by a joint limit lets the integrated yaw
        command run ahead; once it leads by more than pi the IK's shortest rotation turns the
        probe the other way and the error grows (seen: 5 % of navigation expert episodes ended
        150-170 deg off).
        """
        if self.robot is None:
            self.probe_pos, self.probe_rot = self.surface_pose(cmd)
            return
        reached_yaw = self.measured_command()[2]
        lead = wrap_angle(cmd[:, 2] - reached_yaw)
        cmd[:, 2] -= lead - lead.clamp(-MAX_YAW_LEAD, MAX_YAW_LEAD)
        self._cmd[:, : cmd.shape[1]] = cmd
        res = self.controller.step(
            self.q, *self._cmd_args(self._cmd[:, : cmd.shape[1]]), patient=self.patient_index
        )
        self._store(slice(None), res)

    @staticmethod
    def _cmd_args(cmd):
        return cmd[:, 0], cmd[:, 1], cmd[:, 2], (cmd[:, 3] if cmd.shape[1] > 3 else None)

    def _store(self, ids, res) -> None:
        self.q[ids] = res.q.to(self.q.dtype)
        self.probe_pos[ids] = res.pos.float()
        self.probe_rot[ids] = res.rot.float()
        self.reachable[ids] = res.reachable

    def measured_command(self, sl=slice(None)):
        """(x, z, yaw, tilt) of the reached probe poses of the envs ``sl`` (fresh tensors).

        A navigation step reads it four times (the yaw lead, the info, a heading observation,
        episode metrics) between two pose changes, so the envs' values are computed once per
        pose and kept: the cache is keyed on the pose tensors themselves (identity and version
        counter), so any write to ``probe_pos`` or ``probe_rot``, in place or by assignment,
        invalidates it."""
        key = (self.probe_pos, self.probe_rot)
        if torch.is_inference(key[0]) or torch.is_inference(key[1]):  # no version counter
            pid = self.patient_index[sl]
            return self.skin.command_from_pose(self.probe_pos[sl], self.probe_rot[sl], pid)
        versions = (key[0]._version, key[1]._version)
        cached = self._measured
        if cached is None or cached[1] != versions or any(map(operator.is_not, cached[0], key)):
            value = self.skin.command_from_pose(*key, self.patient_index)
            self._measured = cached = (key, versions, value)
        return tuple(t[sl].clone() for t in cached[2])


def probe_track(env, info) -> torch.Tensor:
    """The reached probe pose as a surface command relative to the env's goal command: x, z in
    mm (patient frame, frontal plane), yaw (and tilt, for 4-D commands) in deg; from
    ``info["measured_command"]`` (measured before an in-step reset, so an episode's last point
    is the pose its metrics were taken at)."""
    m, g = info["measured_command"], env.goal_cmd
    out = [(m[:, 0] - g[:, 0]) * 1e3, (m[:, 1] - g[:, 1]) * 1e3]
    out.append(torch.rad2deg(wrap_angle(m[:, 2] - g[:, 2])))
    if g.shape[1] > 3:
        out.append(torch.rad2deg(m[:, 3] - g[:, 3]))
    return torch.stack(out, -1)


def hold_force(env, actions: torch.Tensor) -> torch.Tensor:
    """``actions`` (N, A) of the task's motion, with a force action of 0 (the force held)
    appended when ``env`` has one (``force_action``)."""
    if not getattr(env.cfg, "force_action", False):
        return actions
    return torch.cat([actions, torch.zeros_like(actions[:, :1])], -1)
