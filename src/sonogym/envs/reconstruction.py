"""Task 2, bone-surface reconstruction: scan the target vertebra's dorsal surface, briefly.

**Description.** A probe held on the patient's back by a robot arm scans the target vertebra
(L4). Every step a bone-surface sensor (``sonogym.ultrasound.surface_sensor``) reports the
target's surface seen in the current image plane, and the points are accumulated in a
patient-frame reconstruction volume V: 40 x 40 x 40 voxels of 3 mm (a 120 mm cube) centred on
the centre of the target's bounding box (its whole mask, so the spinous-process tips, ~65 mm
behind the body-weighted centroid, lie inside). The agent plans the probe's path on the skin:
reconstruct much of the surface with a short path and little rotation. The vertebra's pose is
not observed (a POMDP).

*Sensor*: a 50 (lateral) x 80 (depth) px label plane at 1 mm in the probe's image plane; per
scan line the first bone pixel (any bone occludes), kept if it is the target's, then dropped
with probability ``missing_rate`` = 0.2 (paper); kept points map to V by
floor((p - corner) / 3 mm); points outside the cube are discarded. Images are taken from the
pose the arm actually reached. V is cleared at reset and the first image is taken after the
first action, so F(empty) = 0.

*Dorsal reference surface* R (per patient, 40^3 bool): what a probe could see from the back in
a straight posterior view. For every (x, z) column of the patient's voxel grid, the first bone
voxel along +y (anterior) is kept when it belongs to the target and lies within the sensor's
depth (80 mm) of the skin above it; its centre maps into the cube. |M| = |V ∩ R| counts the
reconstructed surface voxels, coverage = |M| / |R| <= 1.

**Observations.** ``obs_mode="reconstruction"`` (default), a Dict:

* ``"reconstruction"``: (40, 40, 40) float32 in {0, 1}, V resampled (nearest) on a
  probe-aligned grid, axes (x_U lateral, y_U elevation, z_U depth): x_U, y_U at
  (i - 19.5) * 3 mm (+-60 mm), z_U at (k + 0.5) * 3 mm below the probe face (0-120 mm);
  samples outside the patient-frame cube read 0;
* ``"path_length"``: (1,) float32, metres, the path so far: the motion that happened, sum over
  steps of the distance the reached probe moved on the frontal (x, z) plane (a step the
  workspace clamp blocks, or the arm does not follow, adds nothing; the reference measures it
  the same way).

``"state"``: (6,) float32, the privileged state (pose of {U} in the vertebra frame {V}:
position m, axis-angle rad), as ``info["state"]``.

**Actions.** (dx, dy, dalpha, dbeta), unitless; scaled by ``action_scale`` (3 mm, 3 mm,
0.1 rad, 0.1 rad) and clipped per component to ``action_limit`` (6 mm, 6 mm, 0.2 rad,
0.2 rad), the documented clipping. dx moves along x_U, dy along the skin tangent
y_U0 = n x x_U (the untilted elevation axis, n the inward skin normal at the reached probe),
both restricted to the frontal (x, z) plane as in navigation; dalpha rotates about the normal
(yaw), dbeta tilts about x_U (docs/design.md, the paper's "pitch"). Documented clamps: the command
(x, z) stays within ``workspace_half_extent`` (60 mm) of the vertebra's centre, yaw within
``yaw_range`` (the navigation arm's workspace, pi +- 2.5 rad), tilt within +-``tilt_limit``
(0.4 rad). ``force_action=True`` (not in the paper) adds a 5th component, the change of the
probe's contact force (1 N per unit, clipped to +-2 N per step, kept in [0, 30] N, from
``contact_force`` at each reset); it compresses the tissue of the images, not the sensor's
bone points (bone does not move).

**Reward.** The marginal gain of the trajectory objective (paper, docs/design.md):

    F(tau_0:t) = |M_0:t| - w2 sum_h (|dx_h| + |dy_h|) - w2 w3 sum_h (|dalpha_h| + |dbeta_h|)

with dx, dy the scaled-and-clipped tangential steps in mm (what is commanded; a step the
workspace clamp blocks still costs), dalpha, dbeta the applied angle increments in rad (after
the yaw and tilt clamps, so a saturated angle costs nothing); w2 = 0.01 per mm, w3 = 100 per
rad. r_t = F(tau_0:t+1) - F(tau_0:t) = (new voxels of M) - 0.01 (|dx| + |dy|) - 1.0 (|dalpha| +
|dbeta|), so an episode's rewards sum to F(tau) - F(empty) = F(tau). On this reward the paper's
"submodular PPO" is plain PPO: the reward already is the marginal gain, and the observation
carries the reconstruction so far (and the path length), as in the reference.

**Randomizations.** Start (x, z) uniform in a 30 x 30 mm square around the vertebra's centre
(paper), yaw uniform in 1.57 +- 0.1 rad (sagittal image), tilt 0; each visible surface point
is missed with probability 0.2, drawn from the env's seeded generator; envs spread over the
configured patients (env i -> patient i % P).

**Termination.** None; truncation after ``episode_length`` = 300 control steps (paper).

**Metrics** (``info["final_info"]`` when an episode ends): ``coverage`` = |M| / |R|;
``total_rotation_deg`` = sum (|dalpha| + |dbeta|) in degrees; ``trajectory_length_mm`` =
the path length of the reached probe positions in mm (as ``path_length``); ``return``.

``info`` every step: ``state`` (N, 6); ``command`` (N, 4) = (x, z, yaw, tilt);
``measured_command`` (N, 4) = (x, z, yaw, tilt) of the reached probe pose (m, rad);
``coverage`` (N,); ``objective`` (N,) float64, F so far; ``covered_voxels`` (N,) |M|;
``visible_points`` / ``sensed_points`` (N,) target surface points in this step's image before
and after dropout; ``reachable`` (N,) bool; ``cost`` (N,) zeros. With a contact force or a
force action: ``contact_force`` (N,) N, ``compression_mm`` (N,) under the image's centre,
``force_cost`` (N,) 1 where the force exceeds ``force_limit``, which is then also ``cost``.

Heuristic: ``heuristic_raster(env)``, the open-loop raster of Li et al. 2023 as the reference
implements it, timed to the episode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Literal, get_args

import numpy as np
import torch
from gymnasium import spaces

from sonogym.anatomy.labels import BONE_IDS, VERTEBRA_IDS
from sonogym.anatomy.patient import Patient
from sonogym.envs.base import SingleEnv
from sonogym.envs.probe_scene import ProbeScene, hold_force, probe_track
from sonogym.envs.scene_config import SceneConfig
from sonogym.envs.spec import (
    EnvMemory,
    Metric,
    TaskSpec,
    Track,
)
from sonogym.envs.task_env import TaskEnv
from sonogym.geometry import normalize, relative_pose, wrap_angle
from sonogym.robots.description import ArmName
from sonogym.ultrasound.surface_sensor import BoneSurfaceSensor

ObsMode = Literal["reconstruction", "state"]
OBS_MODES: tuple[str, ...] = get_args(ObsMode)


@dataclass(frozen=True)
class ReconstructionConfig(SceneConfig):
    """Reconstruction task settings (paper defaults). Every field is a ``make_vec`` keyword.
    ``simulator`` makes the images of ``env.scene.observe("us")``, for viewing only: the
    surface sensor does not read them."""

    obs_modes: ClassVar[tuple[str, ...]] = OBS_MODES

    obs_mode: ObsMode = "reconstruction"  # Dict observation, or the privileged state
    robot: ArmName | None = "kuka_med14"  # probe arm; None: an ideal probe at the command
    start_half_extent: float = 0.015  # m: start (x, z) uniform in +-this around the vertebra
    start_yaw: tuple[float, float] = (1.47, 1.67)  # rad, 1.57 +- 0.1 (sagittal image)
    workspace_half_extent: float = 0.06  # m: command (x, z) clamped to +-this around it
    yaw_range: tuple[float, float] = (math.pi - 2.5, math.pi + 2.5)  # rad, command clamp
    tilt_limit: float = 0.4  # rad, |tilt| clamp (reference)
    action_scale: tuple[float, float, float, float] = (0.003, 0.003, 0.1, 0.1)  # m, m, rad, rad
    action_limit: tuple[float, float, float, float] = (0.006, 0.006, 0.2, 0.2)  # per step
    sensor_width_px: int = 50  # lateral pixels of the surface sensor's label plane (reference)
    sensor_depth_px: int = 80  # depth pixels (reference)
    sensor_spacing: float = 0.001  # m, sensor pixel size (reference)
    missing_rate: float = 0.2  # probability a visible surface point is missed (paper)
    volume_size: int = 40  # voxels per side of the reconstruction cube (paper)
    voxel_size: float = 0.003  # m (paper)
    w2: float = 0.01  # objective weight per mm of path (paper)
    w3: float = 100.0  # per rad: one radian costs as much as 100 mm of path (docs/design.md)
    #: a 5th action, the change of the probe's contact force (``contact_force``; 1 N per unit,
    #: at most 2 N per step, kept in [0, 30] N): the tissue under the probe compresses
    force_action: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.missing_rate <= 1.0:
            raise ValueError(f"missing_rate must be in [0, 1], got {self.missing_rate}")
        if self.target_vertebra not in VERTEBRA_IDS:
            raise ValueError(
                f"target_vertebra {self.target_vertebra!r} is not one of {sorted(VERTEBRA_IDS)}"
            )

    @property
    def cube_half_extent(self) -> float:
        """Half the side of the reconstruction cube, metres (60 mm by default)."""
        return self.volume_size * self.voxel_size / 2


# ---------------------------------------------------------------------------- pure functions


def reconstruction_objective(
    covered: torch.Tensor,
    translation_mm: torch.Tensor,
    rotation_rad: torch.Tensor,
    w2: float = 0.01,
    w3: float = 100.0,
) -> torch.Tensor:
    """F = |M| - w2 sum(|dx| + |dy|) - w2 w3 sum(|dalpha| + |dbeta|).

    ``covered`` (N,) = |M|; ``translation_mm`` (N,) = sum of |dx| + |dy| in mm;
    ``rotation_rad`` (N,) = sum of |dalpha| + |dbeta| in rad. Returns float64 (N,)."""
    return covered.double() - w2 * translation_mm.double() - w2 * w3 * rotation_rad.double()


def reconstruction_reward(
    new_voxels: torch.Tensor,
    step_mm: torch.Tensor,
    step_rad: torch.Tensor,
    w2: float = 0.01,
    w3: float = 100.0,
) -> torch.Tensor:
    """Marginal gain F(tau_0:t+1) - F(tau_0:t) of one step: ``new_voxels`` (N,) newly covered
    surface voxels, ``step_mm`` (N, 2) = (dx, dy) in mm, ``step_rad`` (N, 2) = (dalpha, dbeta)
    in rad. Returns float64 (N,)."""
    return (
        new_voxels.double()
        - w2 * step_mm.double().abs().sum(-1)
        - w2 * w3 * step_rad.double().abs().sum(-1)
    )


def reference_surface(
    patient: Patient,
    target: int,
    corner: np.ndarray,
    voxel: float,
    size: int,
    max_depth: float,
) -> torch.Tensor:
    """The dorsal reference surface R (size^3 bool) of one patient (see the module docstring).

    For every (x, z) column of the patient's voxel grid: the first bone voxel along +y, kept if
    it is the ``target`` label and at most ``max_depth`` (m) below the skin at that column; its
    centre goes to cube voxel floor((p - corner) / voxel)."""
    lab = patient.labels
    lut = torch.zeros(256, dtype=torch.bool)
    lut[sorted(BONE_IDS)] = True
    bone = lut[lab.long()]  # (X, Y, Z)
    has = bone.any(1)
    first = bone.to(torch.uint8).argmax(1)  # (X, Z)
    xs, zs = torch.nonzero(has, as_tuple=True)
    ys = first[xs, zs]
    keep = lab[xs, ys, zs] == target
    xs, ys, zs = xs[keep], ys[keep], zs[keep]
    org = torch.tensor(patient.origin, dtype=torch.float64)
    sp = torch.tensor(patient.spacing, dtype=torch.float64)
    p = org + torch.stack([xs, ys, zs], -1).double() * sp
    skin = patient.skin.height(p[:, 0], p[:, 2])
    p = p[(p[:, 1] - skin) <= max_depth]
    idx = torch.floor((p - torch.tensor(corner, dtype=torch.float64)) / voxel).long()
    idx = idx[((idx >= 0) & (idx < size)).all(-1)]
    vol = torch.zeros(size, size, size, dtype=torch.bool)
    vol[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return vol


def target_box_centre(patient: Patient, target: int) -> np.ndarray:
    """Centre (3,) m of the bounding box of a label's voxels."""
    idx = torch.nonzero(patient.labels == target)
    if len(idx) == 0:
        raise ValueError(f"{patient.name}: label {target} is absent; choose another target")
    lo, hi = idx.min(0).values.numpy(), idx.max(0).values.numpy()
    return patient.origin + (lo + hi) / 2 * patient.spacing


# ---------------------------------------------------------------------------------- env


class ReconstructionEnv(TaskEnv):
    """``SonoGym/Reconstruction-v0`` as a batched env; see the module docstring."""

    def __init__(self, num_envs: int = 1, **kwargs) -> None:
        super().__init__(num_envs, SPEC, kwargs)
        cfg = self.cfg
        self.scene = ProbeScene(cfg, num_envs, self.device, render=False)
        dev, n, size = self.device, num_envs, cfg.volume_size
        pats = self.scene.patients
        pid = self.scene.patient_index
        self.target_label = VERTEBRA_IDS[cfg.target_vertebra]
        self.sensor = BoneSurfaceSensor(
            pats, cfg.sensor_width_px, cfg.sensor_depth_px, cfg.sensor_spacing, device=dev
        )
        max_depth = cfg.sensor_depth_px * cfg.sensor_spacing
        centres = np.stack([target_box_centre(p, self.target_label) for p in pats])
        corners = centres - cfg.cube_half_extent
        self._corner = torch.tensor(corners, dtype=torch.float64, device=dev)  # (P, 3)
        ref = torch.stack(
            [
                reference_surface(p, self.target_label, c, cfg.voxel_size, size, max_depth)
                for p, c in zip(pats, corners, strict=True)
            ]
        ).to(dev)  # (P, S, S, S)
        self._rpad = torch.nn.functional.pad(ref, (1, 1, 1, 1, 1, 1))
        self._reference = self._rpad[:, 1:-1, 1:-1, 1:-1]  # R per patient (view)
        self.reference_voxels = self._reference.flatten(1).sum(1)  # (P,) |R|
        if bool((self.reference_voxels == 0).any()):
            raise ValueError("a patient's target vertebra has no surface visible from the back")
        c = torch.tensor(centres, dtype=torch.float32, device=dev)[pid]
        self.centre = c  # (N, 3) vertebra (bounding-box) centre per env
        # Vertebra-centred command: the start region's centre (the demo's "goal").
        self.goal_cmd = torch.stack(
            [c[:, 0], c[:, 2], torch.full((n,), 1.57, device=dev), torch.zeros(n, device=dev)],
            -1,
        )
        frames = [p.landmarks.vertebra(cfg.target_vertebra) for p in pats]
        self._v_pos = torch.tensor(
            np.stack([f.centre for f in frames]), dtype=torch.float32, device=dev
        )[pid]
        self._v_rot = torch.tensor(
            np.stack([f.rotation for f in frames]), dtype=torch.float32, device=dev
        )[pid]
        self.command = self.goal_cmd.clone()
        self.action_bound = bound = self._set_action_scaling(cfg.action_scale, cfg.action_limit)
        if cfg.obs_mode == "reconstruction":
            obs_space = spaces.Dict(
                {
                    "reconstruction": spaces.Box(0.0, 1.0, (size, size, size), np.float32),
                    "path_length": spaces.Box(0.0, np.inf, (1,), np.float32),
                }
            )
        else:
            obs_space = spaces.Box(-np.inf, np.inf, (6,), np.float32)
        n_act = 4 + cfg.force_action
        self._set_spaces(obs_space, spaces.Box(-bound, bound, (n_act,), np.float32))
        # Per-env episode state.
        p = size + 2  # stored with a one-voxel empty border (cheap out-of-cube lookups)
        # one slot past the cubes: where points outside every cube are written (no masking)
        self._vslots = torch.zeros(n * p**3 + 1, dtype=torch.bool, device=dev)
        self._vpad = self._vslots[:-1].view(n, p, p, p)
        self.volume = self._vpad[:, 1:-1, 1:-1, 1:-1]  # (N, S, S, S) view: V
        self.covered = torch.zeros(n, dtype=torch.long, device=dev)  # |M|
        self.translation_mm = torch.zeros(n, dtype=torch.float64, device=dev)  # sum |dx|+|dy|
        self.rotation_rad = torch.zeros(n, dtype=torch.float64, device=dev)  # sum |da|+|db|
        self.path_mm = torch.zeros(n, dtype=torch.float64, device=dev)  # reached path, mm
        self._reached_xz = torch.zeros(n, 2, dtype=torch.float64, device=dev)  # m
        self.objective = torch.zeros(n, dtype=torch.float64, device=dev)  # F so far
        self.visible_points = torch.zeros(n, dtype=torch.long, device=dev)
        self.sensed_points = torch.zeros(n, dtype=torch.long, device=dev)
        self._reward = torch.zeros(n, dtype=torch.float64, device=dev)
        # Probe-frame observation grid, in units of the cube's voxels.
        g = torch.arange(size, dtype=torch.float32, device=dev)
        self._grid_xy = g - (size - 1) / 2
        self._grid_z = g + 0.5
        self.scene.randomize_imaging(cfg.imaging_randomization)
        self.scene.release_volumes()

    # ------------------------------------------------------------------ hooks
    def _reset_idx(self, env_ids: torch.Tensor) -> None:
        cfg = self.cfg
        cmd = self.draw_surface_starts(env_ids, self.goal_cmd, cfg.start_half_extent, cfg.start_yaw)
        cmd[:, 3] = 0.0
        self.command[env_ids] = cmd
        self.scene.reset(env_ids, cmd)
        self._reached_xz[env_ids] = self._measured_xz(env_ids)
        self.volume[env_ids] = False
        for t in (
            self.covered,
            self.translation_mm,
            self.rotation_rad,
            self.path_mm,
            self.objective,
            self.visible_points,
            self.sensed_points,
        ):
            t[env_ids] = 0
        if self.scene.draws_nets:  # last, so the other draws match model-based runs
            self.scene.draw_nets(env_ids, self.rand(len(env_ids)))
        if self.scene.imaging_randomization is not None:  # after: draws above stay the same
            self.scene.draw_imaging(env_ids, self.rand(len(env_ids), 8))

    def tangent_map(self) -> torch.Tensor:
        """(N, 2, 2) map from a tangential step (dx along x_U, dy along y_U0 = n x x_U) to the
        frontal-plane command change (dx_P, dz_P), at the reached probe poses."""
        pos, rot = self.scene.probe_pos, self.scene.probe_rot
        n = self.scene.skin.normal(pos[:, 0], pos[:, 2], self.scene.patient_index).to(rot)
        xu = rot[:, :, 0]
        yu0 = normalize(torch.linalg.cross(n, xu))
        return torch.stack(
            [torch.stack([xu[:, 0], yu0[:, 0]], -1), torch.stack([xu[:, 2], yu0[:, 2]], -1)], -2
        )

    def _apply_action(self, actions: torch.Tensor) -> None:
        cfg = self.cfg
        if cfg.force_action:
            self.scene.step_force(actions[:, 4])
            actions = actions[:, :4]
        delta = (actions * self.action_scale).clamp(-self.action_limit, self.action_limit)
        m = self.tangent_map()
        dxz = (m @ delta[:, :2].unsqueeze(-1)).squeeze(-1)
        cmd, g, w = self.command, self.goal_cmd, cfg.workspace_half_extent
        before = cmd.clone()
        for i in (0, 1):
            lo, hi = g[:, i] - w, g[:, i] + w
            cmd[:, i] = torch.minimum(torch.maximum(cmd[:, i] + dxz[:, i], lo), hi)
        cmd[:, 2] = (cmd[:, 2] + delta[:, 2]).clamp(*cfg.yaw_range)
        cmd[:, 3] = (cmd[:, 3] + delta[:, 3]).clamp(-cfg.tilt_limit, cfg.tilt_limit)
        self.scene.step(cmd)
        # Accounting (float64): commanded tangential steps in mm, applied angle increments.
        step_mm = delta[:, :2].double() * 1e3
        step_rad = (cmd[:, 2:] - before[:, 2:]).double()
        self.translation_mm += step_mm.abs().sum(-1)
        reached = self._measured_xz(None)
        self.path_mm += (reached - self._reached_xz).norm(dim=-1) * 1e3
        self._reached_xz = reached
        self.rotation_rad += step_rad.abs().sum(-1)
        new = self._sense()
        self._reward = reconstruction_reward(new, step_mm, step_rad, cfg.w2, cfg.w3)
        self.objective += self._reward

    def _measured_xz(self, env_ids: torch.Tensor | None) -> torch.Tensor:
        """(K, 2) frontal-plane position (x, z) of the reached probe poses, m, float64."""
        sl = slice(None) if env_ids is None else env_ids
        x, z, _, _ = self.scene.measured_command(sl)
        return torch.stack([x, z], -1).double()

    def _sense(self) -> torch.Tensor:
        """Image the target's surface from the reached poses, add it to V; returns the newly
        covered reference voxels per env."""
        cfg, size = self.cfg, self.cfg.volume_size
        pid = self.scene.patient_index
        s = self.sensor.sense(
            self.scene.probe_pos,
            self.scene.probe_rot,
            pid,
            self.target_label,
            self._gen,
            cfg.missing_rate,
        )
        self.visible_points = s.visible.sum(1)
        self.sensed_points = s.valid.sum(1)
        idx = torch.floor((s.points - self._corner[pid][:, None]) / cfg.voxel_size).long()
        ok = s.valid & ((idx >= 0) & (idx < size)).all(-1)
        env = torch.arange(self.num_envs, device=self.device)[:, None].expand_as(ok)
        p = size + 2
        idx = idx + 1  # into the padded storage
        vol = p**3
        spare = self.num_envs * vol  # the slot past the cubes
        local = ((idx[..., 0] * p + idx[..., 1]) * p + idx[..., 2]).where(ok, 0)
        flat = torch.where(ok, env * vol + local, spare)
        # New reference voxels: on R, not yet in V, counted once per voxel. Fixed-size ops
        # only (no boolean masks, no unique): no host read, so no wait on a GPU.
        on_r = self._rpad.view(-1)[pid[:, None] * vol + local] & ok
        fresh = on_r & ~self._vslots[flat]
        self._vslots[flat] = True
        key, _ = torch.sort(torch.where(fresh, flat, spare).view(-1))
        first = torch.ones_like(key, dtype=torch.bool)
        first[1:] = key[1:] != key[:-1]
        owner = (key // vol).clamp_max(self.num_envs - 1)
        new = torch.zeros_like(self.covered).index_add_(0, owner, (first & (key != spare)).long())
        self.covered += new
        return new

    def _get_rewards(self) -> torch.Tensor:
        return self._reward.clone()

    def coverage(self, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """|M| / |R| per env (float32)."""
        sl = slice(None) if env_ids is None else env_ids
        ref = self.reference_voxels[self.scene.patient_index[sl]]
        return (self.covered[sl].double() / ref.double()).float()

    def state(self, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """Pose of {U} in the vertebra frame {V}: (K, 6) position (m) and axis-angle (rad)."""
        sl = slice(None) if env_ids is None else env_ids
        p, q = relative_pose(
            self._v_pos[sl], self._v_rot[sl], self.scene.probe_pos[sl], self.scene.probe_rot[sl]
        )
        return torch.cat([p, q], -1).float()

    def probe_frame_reconstruction(self, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """V resampled (nearest) on the probe-aligned 40^3 grid: (K, 40, 40, 40) float32, axes
        (x_U, y_U, z_U); 0 outside the cube."""
        ids = torch.arange(self.num_envs, device=self.device) if env_ids is None else env_ids
        size, vox = self.cfg.volume_size, self.cfg.voxel_size
        p = size + 2  # V is stored with a one-voxel empty border
        k = len(ids)
        pid = self.scene.patient_index[ids]
        rot = self.scene.probe_rot[ids]  # (K, 3, 3); the grid steps one voxel along each axis
        base = ((self.scene.probe_pos[ids].double() - self._corner[pid]) / vox).float()
        gx, gz = self._grid_xy, self._grid_z
        # Flat index into the padded volume, accumulated in float32 (exact: < 2**24): each
        # axis's voxel index, floored and clamped to [-1, size] (the empty border) ...
        acc = torch.empty(k, size, size, size, device=self.device)
        f = torch.empty_like(acc)
        for c in range(3):
            a = (
                base[:, c, None, None]
                + gx[None, :, None] * rot[:, c, 0, None, None]
                + gx[None, None, :] * rot[:, c, 1, None, None]
            )  # (K, S, S): separable in (i, j) and k
            b = gz[None, :] * rot[:, c, 2, None]  # (K, S)
            torch.add(a[..., None], b[:, None, None, :], out=f)
            f.floor_().clamp_(-1, size)
            if c == 0:
                torch.mul(f, p * p, out=acc)
            else:
                acc.add_(f, alpha=p ** (2 - c))
        idx = acc.to(torch.int32)
        # ... + 1 per axis (border offset), + the env's block.
        idx += (ids.to(torch.int32) * p**3 + (p * p + p + 1))[:, None, None, None]
        vals = torch.index_select(self._vpad.view(-1), 0, idx.view(-1))
        return vals.view(k, size, size, size).float()

    def _get_observations(self, env_ids: torch.Tensor | None):
        if self.cfg.obs_mode == "state":
            return self.state(env_ids)
        sl = slice(None) if env_ids is None else env_ids
        return {
            "reconstruction": self.probe_frame_reconstruction(env_ids),
            "path_length": (self.path_mm[sl] * 1e-3).float().unsqueeze(-1),
        }

    def _get_info(self) -> dict:
        info = {
            "state": self.state(),
            "command": self.command.clone(),
            "measured_command": torch.stack(self.scene.measured_command(), -1).float(),
            "coverage": self.coverage(),
            "covered_voxels": self.covered.clone(),
            "objective": self.objective.clone(),
            "visible_points": self.visible_points.clone(),
            "sensed_points": self.sensed_points.clone(),
            "reachable": self.scene.reachable.clone(),
            "cost": torch.zeros(self.num_envs, device=self.device),
            **self.scene.tissue_info(),
        }
        if "force_cost" in info:  # the task's one safety constraint: the force limit
            info["cost"] = info["force_cost"].clone()
        return info

    def _episode_metrics(self, env_ids: torch.Tensor) -> dict[str, torch.Tensor]:
        return {
            "coverage": self.coverage(env_ids),
            "total_rotation_deg": (self.rotation_rad[env_ids] * 180 / math.pi).float(),
            "trajectory_length_mm": self.path_mm[env_ids].float(),
        }

    def coverage_map(self, env: int = 0) -> np.ndarray:
        """Top-down (x right, z up) RGB map of one env's dorsal surface: R grey, reconstructed
        R voxels green, other reconstructed voxels dim red; 40 x 40 x 3 uint8."""
        r = self._reference[self.scene.patient_index[env]].any(1)
        m = (self.volume[env] & self._reference[self.scene.patient_index[env]]).any(1)
        v = self.volume[env].any(1)
        img = np.full((*r.shape, 3), 20, np.uint8)
        img[v.cpu().numpy()] = (120, 40, 40)
        img[r.cpu().numpy()] = (110, 110, 110)
        img[m.cpu().numpy()] = (40, 220, 40)
        return np.ascontiguousarray(img.transpose(1, 0, 2)[::-1])  # rows: z descending

    def _render_frame(self) -> np.ndarray:
        return self.coverage_map(0).repeat(5, 0).repeat(5, 1)


# ---------------------------------------------------------------------------- heuristic


def raster_waypoints(
    columns: tuple[float, ...] = (-0.025, 0.0, 0.025),
    half_length: float = 0.04,
    sweep_yaw: float = math.pi,
    travel_yaw: float = 1.57,
) -> torch.Tensor:
    """Waypoints (W, 4) = (x, z, yaw, tilt) relative to the vertebra's centre (m, rad) of the
    raster of Li et al. 2023 as the reference implements it: for each column x_i, rotate to a
    transverse image (``sweep_yaw``), sweep z from one end to the other, rotate back to a
    sagittal image (``travel_yaw``), step to the next column; alternate sweep directions.
    The reference sweeps with yaw 0; pi is the same transverse plane with x_U flipped, inside
    the arm's workspace (``yaw_range``)."""
    wps = []
    for i, x in enumerate(columns):
        za, zb = (half_length, -half_length) if i % 2 == 0 else (-half_length, half_length)
        wps += [(x, za, travel_yaw), (x, za, sweep_yaw), (x, zb, sweep_yaw), (x, zb, travel_yaw)]
    out = torch.tensor(wps, dtype=torch.float64)
    return torch.cat([out, torch.zeros(len(wps), 1, dtype=torch.float64)], 1)


def raster_reference(
    t: torch.Tensor,
    episode_length: int,
    waypoints: torch.Tensor,
    lead_in: int = 15,
    mm_per_rad: float = 30.0,
) -> torch.Tensor:
    """The raster's reference command at steps ``t`` (N,) relative to the centre: (N, 4).

    The first waypoint is held for ``lead_in`` steps (time to get there from the start), then
    the waypoints are followed piecewise linearly, each segment's duration proportional to its
    length (translation in mm + rotation at ``mm_per_rad``), ending at the last step."""
    d = waypoints[1:] - waypoints[:-1]
    seg = d[:, :2].norm(dim=-1) * 1e3 + d[:, 2:].abs().sum(-1) * mm_per_rad
    ends = torch.cumsum(seg, 0) / seg.sum() * (episode_length - lead_in) + lead_in
    starts = torch.cat([torch.tensor([float(lead_in)], dtype=ends.dtype), ends[:-1]])
    tt = t.double().cpu()
    i = torch.searchsorted(ends, tt, right=False).clamp(max=len(seg) - 1)
    frac = ((tt - starts[i]) / (ends[i] - starts[i])).clamp(0, 1)
    return waypoints[i] + frac[:, None] * d[i]


def heuristic_raster(env: ReconstructionEnv, info: dict | None = None, **kwargs) -> torch.Tensor:
    """Open-loop raster policy (Li et al. 2023; reference ``HeuristicReconstruction``).

    Follows ``raster_reference`` timed by each env's step counter (so it works with partial
    resets): the action drives the command to the next step's reference point, mapped into
    {U} through the env's tangent map and clipped to the action box. ``kwargs`` go to
    ``raster_waypoints``. It never observes the reconstruction.
    """
    cfg = env.cfg
    wps = raster_waypoints(**kwargs)
    ref = raster_reference(env.episode_length_buf + 1, env.episode_length, wps)
    ref = ref.to(env.device, torch.float32)
    target = env.goal_cmd[:, :2] + ref[:, :2]
    err_xz = target - env.command[:, :2]
    m = env.tangent_map()
    step = torch.linalg.solve(m, err_xz.unsqueeze(-1)).squeeze(-1)  # (dx, dy) in m
    err = torch.cat(
        [
            step,
            wrap_angle(ref[:, 2:3] - env.command[:, 2:3]),
            ref[:, 3:4] - env.command[:, 3:4],
        ],
        -1,
    )
    scale = torch.tensor(cfg.action_scale, dtype=err.dtype, device=env.device)
    return hold_force(env, (err / scale).clamp(-env.action_bound, env.action_bound))


def make_single(**kwargs) -> SingleEnv:
    """``gymnasium.make("SonoGym/Reconstruction-v0")``: one env with NumPy I/O."""
    return SingleEnv(ReconstructionEnv, **kwargs)


SPEC = TaskSpec(
    name="reconstruction",
    env_id="SonoGym/Reconstruction-v0",
    env_cls=ReconstructionEnv,
    config_cls=ReconstructionConfig,
    action_names=("dx", "dy", "dalpha", "dbeta"),
    expert=heuristic_raster,
    expert_label="heuristic",
    metrics=(
        Metric("coverage", "coverage ratio", "%", 100.0, better="higher"),
        Metric("total_rotation_deg", "total rotation angle", "deg"),
        Metric("trajectory_length_mm", "trajectory length", "mm"),
    ),
    track=Track(
        ("x", "z", "yaw", "tilt"), ("mm", "mm", "deg", "deg"), probe_track, plane=("x", "z")
    ),
    demo="sonogym.tasks.reconstruction.demo:DEMO",  # how sonogym demo shows it
    agents="sonogym.tasks.reconstruction.agents:TRAINING",  # its RL defaults
    memory=EnvMemory(per_env=2.24e6, per_patient=202e6, load_peak=269e6),  # measured, bytes
)
