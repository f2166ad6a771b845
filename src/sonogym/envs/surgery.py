"""Task 3, ultrasound-guided pedicle drilling: drill along the planned L4 pedicle trajectory.

**Description.** A Franka FR3 holds a 3-D ultrasound probe still on the patient's back, 30 mm
from the target vertebra's midline on the side opposite the drilled pedicle, its image plane
sagittal-ish (x_U along the spine) and tilted 0.4 rad toward the midline. A KUKA LBR Med 14
holds a drill whose tip frame {D} (z_D along the drill axis) the agent moves. The goal frame {G}
sits at the target point of the planned pedicle trajectory (``side`` = right by default), z_G
along the trajectory from entry to target. In {G}:

* C_drill = {sqrt(p_x^2 + p_y^2) <= d/2, -l <= p_z <= 0}, d = 2 (r + 2 mm), r the planned
  corridor radius;
* C_free = {p_z <= -l} (points with p_z = -l count as C_free);
* everything else is unsafe; l = 50 mm, p_l = [0, 0, -l] lies on the trajectory 50 mm before
  the target (docs/design.md).

Probe and drill poses are those the arms reached (forward kinematics after velocity-limited IK).

**Observations.** ``obs_mode="us"`` (default): Dict ``image`` (5, 50, 37) float32 in [0, 1], the
3-D volume (elevation E, depth H, lateral W) at 2 x 2 x 10 mm, and ``pose`` (7,) float32, the
drill tip pose in {U}: position (m) + quaternion (w, x, y, z). ``"ct"``: the image is the CT
volume windowed from [-1000, 2000] HU to [0, 1]; ``"labels"``: the label volume, uint8.
``"state"``: the privileged state (9,): the tip position in {G} (m) and the drill's axes x_D
and z_D in {G} (unit vectors, the first and third columns of R_GD), a continuous encoding of
the pose; ``info["state"]`` keeps position + rotation vector. (Why not the rotation vector:
it jumps where its angle reaches 180 deg, and the drill's free spin about its own axis starts
near 90 deg and drifts there. Why not the goal and z_G seen from the drill, which has no spin:
the corridor's lateral offset then mixes with the tilt times the distance.)
The probe is still and the drill is not imaged, so the volume changes only at resets.

**Actions.** (dp, dw) in {D}, unitless, (6,): scaled by ``action_scale`` (0.1 m, 0.1 m, 0.1 m,
1 rad, 1 rad, 1 rad) and clipped per component to ``action_limit`` (30 mm, 30 mm, 30 mm,
0.1 rad x 3), the documented clipping. Inside C_drill (at the start of the step) the lateral
translation (x_D, y_D) and all three rotation components are then multiplied by
``corridor_damping`` (0.2, the reference's safety shaping; 1 turns it off), so a policy in the
corridor moves 5x slower sideways than along the drill axis. The drill-tip target is the
reached tip pose composed with the body-frame increment: T_target = T_tip (dp, exp(dw)),
its position then kept within ``workspace_radius`` (0.3 m) of {G}'s origin, or within the tip's
current distance where a start lies further out (a start is never pulled in): an exploring
policy cannot wander off, and no action is zeroed (the reference zeroes every action 0.5 m
before the corridor, which freezes the drill there). The
KUKA takes one velocity-limited IK step toward it, so a command faster than the joints allow
leaves a tracking error (``info["tracking_error"]``).

**Reward.** The paper's piecewise reward inside the safe set, weights w4 = 30 per m, w5 = 5
per rad, w6 = 300 per m (the reference implementation's surgery reward works in metres),
written as a potential of the current tip state, plus a penalty per unsafe step:

    Phi(p, theta) = -w5 theta + { w6 (l - |p|)                 if p in C_drill
                                { -w4 |p - p_l|                otherwise (C_free, unsafe)
    r_t = Phi(p_t+1, theta_t+1) - Phi(p_t, theta_t) - unsafe_penalty c_t

theta is the angle between the drill axis z_D and z_G (the drill is symmetric about its axis).
Within C_free this is the paper's w4 (|p_t - p_l| - |p_t+1 - p_l|) + w5 (theta_t - theta_t+1),
within C_drill the paper's w6 (|p_t| - |p_t+1|) + w5 (...); the two agree at p_l.

**Deviation from the paper** (docs/design.md): the paper pays 0 outside the safe set.
That makes leaving free, and with the drill's reach a constant "push along the drill axis"
ends its episodes outside the safe set with more return than standing still (0); the
reference avoided the trap with dense shaping everywhere. Here the unsafe region keeps the
C_free formula's shaping toward p_l (the reference's dense term), so leaving the corridor
gives back everything the insertion earned, and each unsafe step costs ``unsafe_penalty``
(0.3) more: enough that pushing through the target does not pay, small enough that crossing
the corridor's entrance is worth the risk (benchmarks/README.md, "Surgery reward: returns of
simple policies", gives the measured returns).
Being paid for the current state (not the deepest point reached, as a guard on the paper's
formula did before) means backing out of the corridor gives back what going in earned.
Consequences, tested: no closed path earns reward (a potential; a loop through the unsafe
region loses 0.3 per unsafe step), pushing along the drill axis or leaving the corridor and
staying out earns less than standing still, unit-noise dithering earns less than standing
still, reaching depth and backing out earns less than staying, and the expert's return is the
largest of these. The C_free side of the corridor's
entrance has no step: valuing unsafe states lower would make every misaligned crossing of
p_l's plane a cliff, which an exploring policy (5 mm noise against an ~11 mm corridor) learns
to hover above.
Optional (off by default): ``unsafe_distance_penalty`` k (per m) adds k min(dist, cap) per
unsafe step, dist the tip's distance from the safe set (``distance_to_safe_set``) and cap
``unsafe_distance_cap`` (10 mm). A potential cannot tell paths apart, so with the flat
penalty alone a drill that dives beside the corridor below p_l's plane and slides in at depth
earns all the insertion minus 0.3 per unsafe step, which a discount can outweigh; the
distance term charges that path more than grazing the entrance. The cap keeps the early random
walks deep in the unsafe region from costing so much (up to 90 per step at k = w6 uncapped)
that a policy learns to stay out of the corridor.
Cost c_t = 1[p_t+1 unsafe] (``info["cost"]``), for the transition a_t caused.
The ``cpu`` training preset trains with w5 = 50 per rad (``sonogym.tasks.surgery.agents``): at
the paper's 5, 4 deg of tilt cost what 1.2 mm of insertion earns, too little to make a policy
hold the drill aligned (docs/envs.md, "Tilt weight of the cpu training preset"), and with
``CPU_ACTION_LIMIT``, a per-step box the drill arm realises in one step (docs/envs.md, "Action
box of the cpu training preset").

**Randomizations.** Probe: surface (x, z) uniform in +-5 mm around its nominal point, settled
by IK (``obs_mode="state"`` observes no image: there the offset is drawn, so every mode gets the
same drill starts per seed, but the probe is not settled and stays at its nominal pose). Drill:
nominal joints (solved once per patient: tip 90 mm above p_l on the trajectory's continuation,
axis along z_G) + uniform joint noise +-[0.2, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1] rad (the paper's;
``DATA_COLLECTION_JOINT_NOISE`` gives the paper's wider data-collection ranges);
draws whose tip is not in C_free are redrawn (up to 20 times, then the nominal start). Envs
spread over the configured patients (env i -> patient i % P).

**Termination.** None; truncation after ``episode_length`` = 600 control steps.

**Metrics** (``info["final_info"]``): ``insertion_error_mm`` = |p_z| of the final tip;
``side_error_mm`` = sqrt(p_x^2 + p_y^2); ``rotation_error_deg`` = theta; ``safe_ratio`` =
fraction of the states p_1 ... p_T in C_free or C_drill; ``return``.

``info`` every step: ``state`` (N, 6); ``cost`` (N,); ``region`` (N,) int64 (0 C_free,
1 C_drill, 2 unsafe); ``safe`` (N,) bool; ``radius`` (N,) planned corridor radius r (m);
``tracking_error`` (N,) distance (m) between the commanded and reached tip after the step.
With ``contact_force`` > 0 (the still probe pressed; not in the paper): ``contact_force``,
``compression_mm`` under the image's centre and ``force_cost`` (N,), as in navigation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Literal, get_args

import numpy as np
import torch
from gymnasium import spaces

from sonogym.envs import frames
from sonogym.envs.base import SingleEnv
from sonogym.envs.scene_config import SceneConfig
from sonogym.envs.spec import (
    EnvMemory,
    Metric,
    TaskSpec,
    Track,
)
from sonogym.envs.surgery_scene import SIDES, Side, SurgeryScene
from sonogym.envs.task_env import TaskEnv
from sonogym.geometry import (
    axis_angle_from_matrix,
    in_frame,
    matrix_from_axis_angle,
    quat_from_matrix,
)

ObsMode = Literal["us", "ct", "labels", "state"]
OBS_MODES: tuple[str, ...] = get_args(ObsMode)
FREE, DRILL, UNSAFE = 0, 1, 2

#: The paper's joint randomisation for training (rad, uniform +-).
TRAIN_JOINT_NOISE = (0.2, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1)
#: The paper's wider ranges for expert data collection (rad, uniform +-); starts may be unsafe.
DATA_COLLECTION_JOINT_NOISE = (0.3, 0.25, 0.2, 0.2, 0.2, 0.2, 0.1)

_START_REDRAWS = 20

#: The ``cpu`` training preset's per-step action limit (m x3, rad x3): what the drill arm
#: realises in one control step from the corridor's approach (a larger command is slowed whole
#: by the joint speed limits, its axial part too); the spin about the drill axis almost off:
#: the drill is symmetric, so spinning earns nothing, but it turns the observed x_D, and a
#: trained policy that kept spinning drifted out of the corridor late in its episodes.
CPU_ACTION_LIMIT = (0.005, 0.005, 0.01, 0.02, 0.02, 0.001)


@dataclass(frozen=True)
class SurgeryConfig(SceneConfig):
    """Surgery task settings (paper defaults). Every field is a ``make_vec`` keyword."""

    obs_modes: ClassVar[tuple[str, ...]] = OBS_MODES

    obs_mode: ObsMode = "us"
    episode_length: int = 600  # control steps (paper)
    side: Side = "right"  # drilled pedicle, the patient's side
    skin_distance: float = 0.05  # m, l: p_l = [0, 0, -l] in {G} (appendix: 50 mm)
    corridor_margin: float = 0.002  # m, d = 2 (r + corridor_margin)
    start_height: float = 0.09  # m, nominal drill-tip start above p_l (paper: C_free)
    joint_noise: tuple[float, ...] = TRAIN_JOINT_NOISE  # rad, uniform +- per drill joint
    require_free_start: bool = True  # redraw drill starts whose tip is not in C_free
    probe_offset: float = 0.03  # m, probe from the vertebra's midline (paper)
    probe_offset_noise: float = 0.005  # m, uniform +- along both skin axes (paper)
    probe_tilt: float = 0.4  # rad, image plane tilted toward the midline (reference)
    probe_yaw: float = math.pi / 2  # rad, x_U along the spine (reference: 1.57)
    probe_settle_steps: int = 40  # control steps of the probe arm's settle per reset
    gel_depth: float = 0.01  # m, coupling gel under the tilted probe face
    action_scale: tuple[float, ...] = (0.1, 0.1, 0.1, 1.0, 1.0, 1.0)  # m x3, rad x3 per unit
    action_limit: tuple[float, ...] = (0.03, 0.03, 0.03, 0.1, 0.1, 0.1)  # m x3, rad x3 per step
    w4: float = 30.0  # reward per m of progress toward p_l in C_free (paper)
    w5: float = 5.0  # reward per rad of drill-axis alignment (paper)
    w6: float = 300.0  # reward per m of progress toward {G} in C_drill (paper)
    unsafe_penalty: float = 0.3  # reward lost per step that ends in the unsafe region
    # ... plus this much per m of the tip's distance from the safe set, counted up to
    # unsafe_distance_cap (0: off): diving beside the corridor and sliding in at depth then
    # costs more than grazing its entrance
    unsafe_distance_penalty: float = 0.0
    unsafe_distance_cap: float = 0.01  # m
    corridor_damping: float = 0.2  # factor on lateral + rotational actions in C_drill; 1: off
    workspace_radius: float = 0.3  # m: no command takes the tip further from {G}'s origin

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.side not in SIDES:
            raise ValueError(f"side {self.side!r} is not one of {SIDES}")
        if len(self.joint_noise) != 7 or any(v < 0 for v in self.joint_noise):
            raise ValueError(f"joint_noise needs 7 values >= 0 (rad), got {self.joint_noise}")
        for name in ("action_scale", "action_limit"):
            v = getattr(self, name)
            if len(v) != 6 or any(x <= 0 for x in v):
                raise ValueError(f"{name} needs 6 positive values, got {v}")
        if not (self.skin_distance > 0 and self.start_height >= 0):
            raise ValueError("skin_distance must be > 0 and start_height >= 0 (metres)")
        if not 0.0 < self.corridor_damping <= 1.0:
            raise ValueError(f"corridor_damping must be in (0, 1], got {self.corridor_damping}")
        if not self.workspace_radius > 0:
            raise ValueError(f"workspace_radius must be > 0 (m), got {self.workspace_radius}")
        if self.unsafe_penalty < 0:
            raise ValueError(f"unsafe_penalty must be >= 0, got {self.unsafe_penalty}")
        if self.unsafe_distance_penalty < 0 or self.unsafe_distance_cap < 0:
            raise ValueError(
                "unsafe_distance_penalty (per m) and unsafe_distance_cap (m) must be >= 0, got "
                f"{self.unsafe_distance_penalty}, {self.unsafe_distance_cap}"
            )


# ----------------------------------------------------------------------------- pure functions


def drill_angle(rot_gd: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) rotation of {D} in {G} -> (N,) angle (rad) between z_D and z_G."""
    z = rot_gd[..., :, 2]
    return torch.atan2(z[..., :2].norm(dim=-1), z[..., 2])


def surgery_regions(
    p: torch.Tensor, half_width: torch.Tensor, skin_distance: float
) -> torch.Tensor:
    """(N,) region of tip positions p (N, 3) in {G} (m): FREE (p_z <= -l), DRILL
    (sqrt(p_x^2 + p_y^2) <= d/2 and -l < p_z <= 0) or UNSAFE."""
    free = p[:, 2] <= -skin_distance
    drill = ~free & (p[:, :2].norm(dim=-1) <= half_width) & (p[:, 2] <= 0)
    unsafe = torch.full_like(free, UNSAFE, dtype=torch.long)
    return torch.where(free, FREE, torch.where(drill, DRILL, unsafe))


def distance_to_safe_set(
    p: torch.Tensor, half_width: torch.Tensor, skin_distance: float
) -> torch.Tensor:
    """(N,) distance (m) of tip positions p (N, 3) in {G} from C_free U C_drill: 0 inside,
    else the nearer of p_l's plane (p_z = -l) and the corridor cylinder (radius d/2, depth 0)."""
    radial = (p[:, :2].norm(dim=-1) - half_width).clamp_min(0.0)
    to_corridor = torch.hypot(radial, p[:, 2].clamp_min(0.0))
    to_plane = (p[:, 2] + skin_distance).clamp_min(0.0)
    return torch.minimum(to_corridor, to_plane)


def surgery_potential(
    p: torch.Tensor,
    theta: torch.Tensor,
    region: torch.Tensor,
    skin_distance: float,
    w4: float,
    w5: float,
    w6: float,
) -> torch.Tensor:
    """Phi of tip states (see the module docstring): p (N, 3) m in {G}, theta (N,) rad, region
    (N,) FREE, DRILL or UNSAFE.

    C_drill: w6 (l - |p|) - w5 theta; C_free and unsafe: -w4 |p - p_l| - w5 theta (the two
    agree at p_l)."""
    p_l = torch.zeros_like(p)
    p_l[:, 2] = -skin_distance
    outside = -w4 * (p - p_l).norm(dim=-1)
    drill = w6 * (skin_distance - p.norm(dim=-1))
    return torch.where(region == DRILL, drill, outside) - w5 * theta


def surgery_reward(
    p: torch.Tensor,
    theta: torch.Tensor,
    p_next: torch.Tensor,
    theta_next: torch.Tensor,
    half_width: torch.Tensor,
    skin_distance: float,
    w4: float,
    w5: float,
    w6: float,
    unsafe_penalty: float,
    unsafe_distance_penalty: float = 0.0,
    unsafe_distance_cap: float = math.inf,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One transition: reward Phi(s_t+1) - Phi(s_t) - (unsafe_penalty + unsafe_distance_penalty
    min(dist(p_t+1, safe set), unsafe_distance_cap)) c_t, cost c_t = 1[p_t+1 unsafe] and the
    region of p_t+1 (module docstring).

    p, p_next: (N, 3) tip positions in {G} before and after, m; theta, theta_next: (N,) drill-axis
    angles, rad; half_width: (N,) d/2 = r + 2 mm, m."""
    l = skin_distance
    region = surgery_regions(p, half_width, l)
    region_next = surgery_regions(p_next, half_width, l)
    phi = surgery_potential(p, theta, region, l, w4, w5, w6)
    phi_next = surgery_potential(p_next, theta_next, region_next, l, w4, w5, w6)
    cost = (region_next == UNSAFE).to(p_next.dtype)
    penalty = unsafe_penalty * cost
    if unsafe_distance_penalty:
        d = distance_to_safe_set(p_next, half_width, l).clamp_max(unsafe_distance_cap)
        penalty = penalty + unsafe_distance_penalty * cost * d
    return phi_next - phi - penalty, cost, region_next


def clamp_to_ball(points: torch.Tensor, centre: torch.Tensor, radius: torch.Tensor | float):
    """(N, 3) points moved radially onto the ball of ``radius`` (m, scalar or (N,)) around
    ``centre`` (N, 3) where they lie outside it; points inside are unchanged."""
    offset = points - centre
    norm = offset.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    radius = torch.as_tensor(radius, dtype=points.dtype, device=points.device).reshape(-1, 1)
    return centre + offset * (radius / norm).clamp(max=1.0)


def state_observation(state: torch.Tensor) -> torch.Tensor:
    """(N, 6) tip states in {G} (position m + rotation vector of {D} in {G}, rad) -> (N, 9)
    the observation ``obs_mode="state"``: the position, then x_D and z_D in {G} (columns 0 and
    2 of R_GD), continuous in the pose where the rotation vector is not (at 180 deg)."""
    r_gd = matrix_from_axis_angle(state[:, 3:])
    return torch.cat([state[:, :3], r_gd[..., :, 0], r_gd[..., :, 2]], -1)


def corridor_damping(delta: torch.Tensor, in_corridor: torch.Tensor, factor: float):
    """The reference's safety shaping: inside C_drill the lateral translation (x_D, y_D) and
    every rotation component of the scaled, clipped action ``delta`` (N, 6) are multiplied by
    ``factor``; elsewhere, and along the drill axis z_D, the action is unchanged."""
    scale = torch.tensor([factor, factor, 1.0, factor, factor, factor], device=delta.device)
    return torch.where(in_corridor[:, None], delta * scale.to(delta.dtype), delta)


def surgery_expert(
    state: torch.Tensor,
    radius: torch.Tensor,
    skin_distance: float = 0.05,
    approach: float = 0.01,
    stop_short: float = 2e-4,
    position_gain: float = 0.1,
    rotation_gain: float = 0.1,
    max_step: float = 0.01,
    max_rotation: float = 0.05,
    action_scale: tuple[float, ...] = (0.1, 0.1, 0.1, 1.0, 1.0, 1.0),
) -> torch.Tensor:
    """The paper's expert from the true state: to the skin point first, then along the
    trajectory to {G} (reference ExpertSurgery, gains retuned for the kinematic arm).

    ``state`` (N, 6) is the tip pose in {G} (``info["state"]``: position m, rotation vector
    rad), ``radius`` (N,) the planned corridor radius r (``info["radius"]``). The waypoint is
    the axis point ``stop_short`` before {G} (the target lies on C_drill's boundary p_z = 0, so
    a controller converging onto it would cross it by rounding) once the tip is within r of the
    trajectory axis with sin(theta) < 0.2 (reference), or already past p_l inside the corridor
    (within r + 2 mm of the axis); before that it is the axis point
    ``approach`` above p_l (in C_free, so the approach never grazes the unsafe region); a tip
    off the corridor and below that height first backs out along -z_G. Action:
    ``position_gain`` x the waypoint error in {D} (at most ``max_step`` m) and ``rotation_gain``
    x the rotation vector turning z_D onto z_G, in {D} (at most ``max_rotation`` rad), in
    action units.
    """
    p, r_gd = state[:, :3], matrix_from_axis_angle(state[:, 3:])
    z_d = r_gd[:, :, 2]
    lateral = p[:, :2].norm(dim=-1)
    sin_t = z_d[:, :2].norm(dim=-1)
    inserting = ((lateral < radius) & (sin_t < 0.2)) | (
        (p[:, 2] > -skin_distance) & (lateral < radius + 0.002)
    )
    waypoint = torch.zeros_like(p)
    waypoint[:, 2] = torch.where(inserting, -stop_short, -(skin_distance + approach))
    # Off the corridor and not well above p_l's plane (only unsafe or data-collection starts):
    # back out along -z_G first, then approach.
    back_out = ~inserting & (lateral >= radius) & (p[:, 2] > -(skin_distance + approach / 2))
    waypoint[:, :2] = torch.where(back_out[:, None], p[:, :2], waypoint[:, :2])
    err_d = (r_gd.transpose(-1, -2) @ (waypoint - p).unsqueeze(-1)).squeeze(-1)
    dp = position_gain * err_d
    n = dp.norm(dim=-1, keepdim=True)
    dp = dp * (max_step / n.clamp_min(1e-12)).clamp(max=1.0)
    # rotation turning z_D onto z_G, expressed in {D}: axis z_D x z_G, angle theta
    e_z = torch.zeros_like(z_d)
    e_z[:, 2] = 1.0
    axis_g = torch.linalg.cross(z_d, e_z)
    s = axis_g.norm(dim=-1, keepdim=True)
    theta = torch.atan2(s, z_d[:, 2:3])
    rotvec_g = axis_g / s.clamp_min(1e-12) * theta
    dw = rotation_gain * (r_gd.transpose(-1, -2) @ rotvec_g.unsqueeze(-1)).squeeze(-1)
    m = dw.norm(dim=-1, keepdim=True)
    dw = dw * (max_rotation / m.clamp_min(1e-12)).clamp(max=1.0)
    scale = torch.tensor(action_scale, dtype=state.dtype, device=state.device)
    return (torch.cat([dp, dw], -1) / scale).float()


# ----------------------------------------------------------------------------- the env


class SurgeryEnv(TaskEnv):
    """``SonoGym/Surgery-v0`` as a batched env; see the module docstring."""

    def __init__(self, num_envs: int = 1, **kwargs) -> None:
        super().__init__(num_envs, SPEC, kwargs)
        cfg = self.cfg
        self.scene = SurgeryScene(cfg, num_envs, self.device, render=cfg.obs_mode != "state")
        n, dev = num_envs, self.device
        f32 = dict(dtype=torch.float32, device=dev)
        self.half_width = self.scene.radius + cfg.corridor_margin  # (N,) d/2, m
        self._set_action_scaling(cfg.action_scale, cfg.action_limit)
        self.joint_noise = torch.tensor(cfg.joint_noise, **f32)
        bound = (self.action_limit / self.action_scale).cpu().numpy()
        img_shape = self.scene.image_shape
        # tip position in {U} (m; the arms' reach bounds it well within 3 m) + unit quaternion
        pose = spaces.Box(
            np.array([-3.0] * 3 + [-1.0] * 4, np.float32),
            np.array([3.0] * 3 + [1.0] * 4, np.float32),
            dtype=np.float32,
        )
        if cfg.obs_mode == "state":
            obs_space = spaces.Box(-np.inf, np.inf, (9,), np.float32)
        elif cfg.obs_mode == "labels":
            obs_space = spaces.Dict(
                {"image": spaces.Box(0, 255, img_shape, np.uint8), "pose": pose}
            )
        else:
            obs_space = spaces.Dict(
                {"image": spaces.Box(0.0, 1.0, img_shape, np.float32), "pose": pose}
            )
        self._set_spaces(obs_space, spaces.Box(-bound, bound, (6,), np.float32))
        img_dtype = torch.uint8 if cfg.obs_mode == "labels" else torch.float32
        self._image = torch.zeros(n, *img_shape, dtype=img_dtype, device=dev)
        self._state = torch.zeros(n, 6, **f32)
        self._theta = torch.zeros(n, **f32)
        self._region = torch.zeros(n, dtype=torch.long, device=dev)
        self._cost = torch.zeros(n, **f32)
        self._safe_steps = torch.zeros(n, **f32)
        self._tracking_error = torch.zeros(n, **f32)
        self.start_redraws = torch.zeros(n, dtype=torch.long, device=dev)
        self.scene.randomize_imaging(cfg.imaging_randomization)
        self.scene.release_volumes()

    # ------------------------------------------------------------------ hooks
    def _reset_idx(self, env_ids: torch.Tensor) -> None:
        cfg, sc, k = self.cfg, self.scene, len(env_ids)
        h = cfg.probe_offset_noise
        offset = self.uniform(-h, h, k, 2).float()  # drawn in every mode: same starts per seed
        if cfg.obs_mode != "state":
            # nothing observes the probe in state mode; its 40-step settle was half the CPU
            # time of a state-mode training run
            sc.reset_probe(env_ids, offset)
        # Drill start: nominal joints + noise; redraw starts whose tip is not in C_free.
        q = sc.drill_start_joints(env_ids, self._joint_noise(k))
        redraws = torch.zeros(k, dtype=torch.long, device=self.device)
        if cfg.require_free_start:
            for _ in range(_START_REDRAWS):
                pos, _ = sc.drill_fk(env_ids, q)
                bad = self._regions_at(env_ids, pos) != FREE
                if not bool(bad.any()):
                    break
                redraws += bad.long()
                q_new = sc.drill_start_joints(env_ids, self._joint_noise(k))
                q = torch.where(bad[:, None], q_new, q)
            else:
                pos, _ = sc.drill_fk(env_ids, q)
                bad = self._regions_at(env_ids, pos) != FREE
                q = torch.where(bad[:, None], sc.drill_start_joints(env_ids, 0 * q), q)
        self.start_redraws[env_ids] = redraws
        sc.set_drill(env_ids, q)
        state, theta = self._measure(env_ids)
        self._state[env_ids], self._theta[env_ids] = state, theta
        region = surgery_regions(state[:, :3], self.half_width[env_ids], cfg.skin_distance)
        self._region[env_ids] = region
        self._cost[env_ids] = 0.0
        self._safe_steps[env_ids] = 0.0
        self._tracking_error[env_ids] = 0.0
        if sc.draws_nets:  # last, so the other draws match model-based runs
            sc.draw_nets(env_ids, self.rand(k))
        if sc.imaging_randomization is not None:  # after: draws above stay the same
            sc.draw_imaging(env_ids, self.rand(k, 8))
        # The probe is still for the episode: image the volume once (it does not see the drill).
        if cfg.obs_mode != "state":
            self._image[env_ids] = sc.observe(cfg.obs_mode, env_ids)

    def _joint_noise(self, k: int) -> torch.Tensor:
        return self.uniform(-1.0, 1.0, k, 7).float() * self.joint_noise

    def _regions_at(self, env_ids: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        p, _ = in_frame(self.scene.goal_pos[env_ids], self.scene.goal_rot[env_ids], pos)
        return surgery_regions(p, self.half_width[env_ids], self.cfg.skin_distance)

    def _apply_action(self, actions: torch.Tensor) -> None:
        cfg, sc = self.cfg, self.scene
        delta = torch.maximum(
            torch.minimum(actions * self.action_scale, self.action_limit), -self.action_limit
        )
        if cfg.corridor_damping != 1.0:
            delta = corridor_damping(delta, self._region == DRILL, cfg.corridor_damping)
        target_pos = sc.tip_pos + (sc.tip_rot @ delta[:, :3].unsqueeze(-1)).squeeze(-1)
        # the workspace: no command ends further from {G} than workspace_radius, or than the
        # tip already is (a start outside is not pulled in)
        reach = (sc.tip_pos - sc.goal_pos).norm(dim=-1).clamp_min(cfg.workspace_radius)
        target_pos = clamp_to_ball(target_pos, sc.goal_pos, reach)
        target_rot = sc.tip_rot @ matrix_from_axis_angle(delta[:, 3:])
        res = sc.step_drill(target_pos, target_rot)
        self._tracking_error = (target_pos - res.pos).norm(dim=-1)
        state, theta = self._measure(None)
        reward, cost, region = surgery_reward(
            self._state[:, :3],
            self._theta,
            state[:, :3],
            theta,
            self.half_width,
            cfg.skin_distance,
            cfg.w4,
            cfg.w5,
            cfg.w6,
            cfg.unsafe_penalty,
            cfg.unsafe_distance_penalty,
            cfg.unsafe_distance_cap,
        )
        self._reward = reward
        self._cost = cost
        self._region = region
        self._state, self._theta = state, theta
        self._safe_steps += (region != UNSAFE).float()

    def _measure(self, env_ids: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        sl = slice(None) if env_ids is None else env_ids
        p, r_gd = self.scene.tip_in_goal(sl)
        return torch.cat([p, axis_angle_from_matrix(r_gd)], -1).float(), drill_angle(r_gd)

    def _get_rewards(self) -> torch.Tensor:
        return self._reward

    def _get_observations(self, env_ids: torch.Tensor | None):
        sl = slice(None) if env_ids is None else env_ids
        if self.cfg.obs_mode == "state":
            return state_observation(self._state[sl])
        p, r_ud = self.scene.tip_in_probe(sl)
        pose = torch.cat([p, quat_from_matrix(r_ud)], -1).float()
        return {"image": self._image[sl].clone(), "pose": pose}

    def _get_info(self) -> dict:
        return {
            "state": self._state.clone(),
            "cost": self._cost.clone(),
            "region": self._region.clone(),
            "safe": self._region != UNSAFE,
            "radius": self.scene.radius.clone(),
            "tracking_error": self._tracking_error.clone(),
            **self.scene.tissue_info(),
        }

    def errors(self, env_ids: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Insertion error (|p_z|, mm), side error (sqrt(p_x^2 + p_y^2), mm) and rotation error
        (angle between z_D and z_G, deg) of the reached tip."""
        sl = slice(None) if env_ids is None else env_ids
        p = self._state[sl, :3]
        return {
            "insertion_error_mm": p[:, 2].abs() * 1e3,
            "side_error_mm": p[:, :2].norm(dim=-1) * 1e3,
            "rotation_error_deg": self._theta[sl] * (180.0 / math.pi),
        }

    def _episode_metrics(self, env_ids: torch.Tensor) -> dict[str, torch.Tensor]:
        out = self.errors(env_ids)
        steps = self.episode_length_buf[env_ids].clamp_min(1).float()
        out["safe_ratio"] = self._safe_steps[env_ids] / steps
        return out

    def volume(self, env: int) -> torch.Tensor:
        """(E, H, W) image volume of env ``env`` (imaged at its last reset)."""
        return self._image[env]

    def _render_frame(self) -> np.ndarray:
        return frames.surgery_frame(self, self._state[:1, :3].cpu().numpy())


def make_single(**kwargs) -> SingleEnv:
    """``gymnasium.make("SonoGym/Surgery-v0")``: one env with NumPy I/O."""
    return SingleEnv(SurgeryEnv, **kwargs)


def expert(env: SurgeryEnv, info: dict) -> torch.Tensor:
    """The paper's expert on ``env`` (``surgery_expert`` from the privileged state)."""
    return surgery_expert(
        info["state"],
        info["radius"],
        skin_distance=env.cfg.skin_distance,
        action_scale=env.cfg.action_scale,
    )


def drill_track(env, info) -> torch.Tensor:
    """Drill tip in the goal frame {G} (mm): z along the planned trajectory, 0 at the target."""
    return info["state"][:, :3] * 1e3


SPEC = TaskSpec(
    name="surgery",
    env_id="SonoGym/Surgery-v0",
    env_cls=SurgeryEnv,
    config_cls=SurgeryConfig,
    action_names=("dx", "dy", "dz", "wx", "wy", "wz"),
    expert=expert,
    expert_label="expert",
    metrics=(
        Metric("side_error_mm", "side err", "mm"),
        Metric("insertion_error_mm", "insert err", "mm"),
        Metric("rotation_error_deg", "rot err", "deg"),
        Metric("safe_ratio", "safe ratio", "%", 100.0, better="higher"),
    ),
    track=Track(("x", "y", "z"), ("mm", "mm", "mm"), drill_track, plane=("x", "z"), axis_line=True),
    demo="sonogym.tasks.surgery.demo:DEMO",  # how sonogym demo shows it
    # "state" 2: position + x_D, z_D in {G} (state_observation); 1: position + rotation vector
    obs_versions={"state": 2},
    agents="sonogym.tasks.surgery.agents:TRAINING",  # its RL defaults
    memory=EnvMemory(per_env=0.81e6, per_patient=196e6, load_peak=23e6),  # measured, bytes
    dataset="sonogym.tasks.surgery.dataset:DATASET",  # its expert datasets
)
