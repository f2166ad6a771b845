"""A probe held on the back of each env's patient by a robot arm, and its images.

Shared by the navigation and reconstruction tasks: per-env patients (env i -> patient i % P),
their stacked skin surfaces, the arm that tracks surface commands (or an ideal probe when
``robot=None``), and slicing + simulation of the pose the arm actually reached.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
import torch

from sonogym.anatomy import SkinSurface
from sonogym.envs.imaging import (
    DEFAULT_LEARNED_NETS,
    SIMULATORS,
    NetChoice,
    build_simulator,
    check_simulator,
    simulate_us,
)
from sonogym.envs.patients import resolve_patients
from sonogym.geometry import wrap_angle

#: CT window of the "ct" observation mode, HU -> [0, 1].
CT_WINDOW = (-1000.0, 2000.0)
#: rad: the commanded yaw is held within this of the yaw the arm reached (anti-windup).
MAX_YAW_LEAD = 0.5
__all__ = ["CT_WINDOW", "SIMULATORS", "ProbeScene", "image_observation"]


class ProbeScene:
    """Probe arm + patients + imaging for N envs.

    Args:
        patients: phantom seeds and/or TotalSegmentator folders.
        num_envs: N.
        spacing: voxel size (m) of phantoms / resampled folders.
        simulator: "physical" or "sonogym" (model-based presets) or "learned".
        robot: arm model name ("kuka_med14", "franka_fr3") or None for an ideal probe.
        target_vertebra: the vertebra whose body centroid anchors goals and arm placement.
        device: torch device of everything.
        render: build the slicer and simulator now (else on first ``observe``).
        probe: the imaging geometry (default: the paper's 2-D linear probe).
        learned_nets: nets of ``simulator="learned"`` (ints: shipped nets, str: weight files);
            each env uses ``nets.index`` into them, redrawn by ``draw_nets`` at its resets.
    """

    def __init__(
        self,
        patients,
        num_envs: int,
        spacing: float,
        simulator: str,
        robot: str | None,
        target_vertebra: str,
        device: torch.device,
        render: bool = True,
        probe=None,
        learned_nets=DEFAULT_LEARNED_NETS,
    ) -> None:
        check_simulator(simulator, learned_nets)
        self.device = device
        self.learned_nets = tuple(learned_nets)
        self.nets = NetChoice(num_envs, len(self.learned_nets), device)
        self.num_envs = num_envs
        self.patients = resolve_patients(patients, spacing)
        self.patient_index = torch.arange(num_envs, device=device) % len(self.patients)
        self.simulator_name = simulator
        self._probe = probe
        self.skin = SkinSurface.stack([p.skin for p in self.patients]).to(device)
        centres = torch.tensor(
            np.array([p.landmarks.vertebra(target_vertebra).centre for p in self.patients]),
            dtype=torch.float32,
            device=device,
        )
        self.target_centres = centres[self.patient_index]
        self.robot = robot
        self.probe_pos = torch.zeros(num_envs, 3, device=device)
        self.probe_rot = torch.eye(3, device=device).repeat(num_envs, 1, 1)
        self.reachable = torch.ones(num_envs, dtype=torch.bool, device=device)
        self._cmd = torch.zeros(
            num_envs, 4, device=device
        )  # last command per env (x, z, yaw, tilt)
        if robot is not None:
            self._init_robot(robot)
        if render:
            _ = self.slicer, self.simulator

    @classmethod
    def from_config(cls, cfg, num_envs: int, device: torch.device, render: bool) -> ProbeScene:
        """The scene of a probe task's config (its ``patients``, ``phantom_spacing``,
        ``simulator``, ``learned_nets``, ``robot`` and ``target_vertebra`` fields)."""
        return cls(
            cfg.patients,
            num_envs,
            spacing=cfg.phantom_spacing,
            simulator=cfg.simulator,
            learned_nets=cfg.learned_nets,
            robot=cfg.robot,
            target_vertebra=cfg.target_vertebra,
            device=device,
            render=render,
        )

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
        joints and settles onto the pose (the reference's settle phase)."""
        if self.robot is None:
            pos, rot = self.surface_pose(cmd, env_ids)
            self.probe_pos[env_ids], self.probe_rot[env_ids] = pos, rot
            self.reachable[env_ids] = True
            return
        # The arms share one batched kinematics object (per-env bases), so the settle runs over
        # every env and keeps the result of the reset ones; the others' state is untouched.
        q = self.q.clone()
        q[env_ids] = self.arm.default_joints(len(env_ids)).to(q.dtype)
        full = self._cmd.clone()
        full[env_ids, : cmd.shape[1]] = cmd
        res = self.controller.settle(q, *self._cmd_args(full), patient=self.patient_index)
        self._cmd[env_ids] = full[env_ids]
        self._store(env_ids, _select(res, env_ids))

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
        self.probe_pos[ids] = res.probe_pos.float()
        self.probe_rot[ids] = res.probe_rot.float()
        self.reachable[ids] = res.reachable

    def measured_command(self, sl=slice(None)):
        """(x, z, yaw, tilt) of the reached probe poses."""
        pid = self.patient_index[sl]
        return self.skin.command_from_pose(self.probe_pos[sl], self.probe_rot[sl], pid)

    # ---------------------------------------------------------------- imaging
    @cached_property
    def slicer(self):
        from sonogym.ultrasound import ProbeGeometry, Slicer

        return Slicer(self.patients, self._probe or ProbeGeometry.linear_2d(), device=self.device)

    @cached_property
    def simulator(self):
        return build_simulator(self.simulator_name, self.patients, self.device, self.learned_nets)

    def draw_nets(self, env_ids: torch.Tensor, u: torch.Tensor) -> None:
        """Draw the learned net of each env in ``env_ids`` from uniforms ``u`` (see NetChoice)."""
        self.nets.draw(env_ids, u)

    @property
    def image_shape(self) -> tuple[int, int]:
        from sonogym.ultrasound import ProbeGeometry

        probe = self._probe or ProbeGeometry.linear_2d()
        return probe.depth_px, probe.width_px

    def slices(self, env_ids: torch.Tensor | None = None):
        sl = slice(None) if env_ids is None else env_ids
        return self.slicer(self.probe_pos[sl], self.probe_rot[sl], self.patient_index[sl])

    def observe(self, mode: str, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """Images of the reached poses (see ``image_observation``)."""
        return image_observation(self.slices(env_ids), mode, self, env_ids)


def image_observation(slices, mode: str, scene, env_ids=None) -> torch.Tensor:
    """An image observation of sliced CT + labels: "us" the ultrasound simulated by
    ``scene.simulator`` (N, E, H, W) in [0, 1] (the simulator is built only for this mode; the
    learned one uses each env's net), "ct" the CT windowed from ``CT_WINDOW`` to [0, 1],
    "labels" the uint8 ids. ``env_ids``: the envs the slices belong to (None: all)."""
    if mode == "us":
        return simulate_us(scene, slices, env_ids).float()
    if mode == "ct":
        lo, hi = CT_WINDOW
        return ((slices.ct - lo) / (hi - lo)).clamp(0, 1)
    if mode == "labels":
        return slices.labels
    raise ValueError(f"unknown image mode {mode!r}")


def _select(res, ids):
    """Rows ``ids`` of every tensor field of a controller result."""
    import dataclasses

    return type(res)(**{f.name: getattr(res, f.name)[ids] for f in dataclasses.fields(res)})
