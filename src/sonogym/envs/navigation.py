"""Task 1, ultrasound navigation: bring the probe to the transverse view above L4.

**Description.** A probe held on the patient's back by a robot arm starts at a random pose and
must reach the goal frame {G}: the transverse view (yaw alpha_G = pi) centred on the target
vertebra, the probe on the skin point whose beam (the skin's smoothed inward normal) passes
through the vertebra's body centroid (``goal_commands``; task version 2). The arm keeps the
probe on the skin with its beam along the inward normal; the agent plans the 3 tangential DoF.

**Observations.** ``obs_mode="us"``: the ultrasound image, (1, 200, 150) float32 in [0, 1] (depth
rows from the probe face, lateral columns). ``"ct"``: the CT slice mapped from [-1000, 2000] HU
to [0, 1]. ``"labels"``: the label slice, uint8 ids. ``"state"``: the privileged state (6,).
``"us_heading"`` (not in the paper): Dict ``image``, the ultrasound image as in ``"us"``, and
``heading`` (2,) float32 = (cos alpha, sin alpha) of the reached probe's yaw alpha in the
patient's frontal plane (the angle the goal's alpha_G = pi is measured in). Why: the transverse
view is nearly mirror-symmetric (at the goal position, the goal image and the image at yaw 0
mirrored left-right correlate 0.78-0.85 in ultrasound), so an image-only policy can hardly
tell the goal from the goal turned 180 deg; 10-12 % of an image-only population run's
episodes ended there, none with the heading. The heading is what a
tracked probe tells about the patient lying on the bed; it says nothing of where the goal lies.
``"us_memory"`` (not in the paper): ``us_heading`` with a memory of the scan. Dict ``image``
(2, 200, 150): the current image and the image ``memory_lag`` control steps earlier (the
episode's first image until the episode is that old; kept at 8 bits, steps of 1/255);
``heading`` (4,): (cos, sin) of the reached yaw now and then; ``motion`` (2,) m: the reached
probe's displacement in the frontal plane (x, z of {P}) since the remembered image. Why: one
transverse image locates the goal hardly better than "near the goal" (benchmarks/README.md,
"Navigation: how much of the goal the image shows"); given also the image 30 steps back and
the motion since, a supervised probe's median error near the goal falls from ~12 mm to 9.5 mm
on held-out phantoms and 8.6 mm on the real subject (task version 1). Everything it adds is
what the arm's own pose tracking and the images already seen tell; nothing of where the goal
lies.
``"us_scan"`` (not in the paper): ``us_memory`` with the caudal end of the scan as well. Dict
``image`` (3, 200, 150): ``us_memory``'s two images and the image taken where the reached probe
was most caudal (lowest z of {P}) so far this episode (8 bits); ``heading`` (6,): ``us_memory``'s
and (cos, sin) of the yaw there; ``motion`` (4,) m: ``us_memory``'s and the frontal-plane
displacement (x, z) from there. Why: a policy with a 30-step memory counts levels up from the
sacrum but not down from L1: from cranial starts it stops over L3's arch, which looks like L4's
(docs/envs.md). Sonographers count from the sacrum; the caudal end of the scan keeps the
lowest level visited in view however long ago, so a probe that went down to L5 or the sacrum
and came back knows how far above it is. Like ``us_memory``, only what the pose tracking and
the images already seen tell.
``observe_tilt=True`` (not in the paper; with ``us_heading``, ``us_memory`` or ``us_scan``)
adds ``tilt`` (2,) float32 = ``probe_tilt``: the patient's vertical +y_P seen in the image's
lateral and elevation axes (the sines of the beam's tilt). Why: the beam follows the skin's
smoothed inward normal, which at the goal leans -12.5..+18.8 deg sideways on phantoms and the
real subject, so the arch sits up to ~15 mm off the image's centre line at the goal, by an
amount an image alone cannot tell from the probe being off the goal. Trained with it, PPO ends
closer across the spine on new phantoms but fails on the real subject (docs/envs.md): off by
default.

**Actions.** (dx, dy, dalpha) in {U}, unitless; scaled by ``action_scale`` (3 mm, 3 mm, 0.1 rad)
and clipped per component to ``action_limit`` (6 mm, 6 mm, 0.2 rad), the documented clipping.
dx moves along x_U, dy along y_U (both on the skin), dalpha rotates about the normal. The
surface command (x, z, alpha) stays within ``workspace_half_extent`` of {G} and alpha within
``yaw_range`` (clamped, documented). ``force_action=True`` (not in the paper) adds a 4th
component, the change of the probe's contact force (1 N per unit, clipped to +-2 N per step,
the force kept in [0, 30] N; it starts each episode at ``contact_force``): the tissue under the
probe compresses (``sonogym.ultrasound.compression``).

**Reward.** r_t = w1 (||p_t|| - ||p_t+1||) + ||q_t|| - ||q_t+1||, with p (mm) and q (axis-angle,
rad) the pose of {U} in {G} before and after the transition caused by a_t; w1 = 0.045 per mm.

**Randomizations.** Start (x, z) uniform in a 130 x 130 mm square centred on {G}, alpha uniform
in [1.5, 3.5] rad; envs spread over the configured patients (env i -> patient i % P).

**Termination.** None; truncation after ``episode_length`` = 300 control steps.

**Metrics** (``info["final_info"]`` when an episode ends): ``position_error_mm`` = frontal-plane
(x, z) distance of the reached probe from {G}; ``angle_error_deg`` = |wrap(alpha - alpha_G)|;
``level_miss`` = 1 where the probe ended more than ``LEVEL_MISS_MM`` from {G} along the spine
(a neighbouring vertebra's view), else 0 (its mean over episodes is the level-miss rate);
``return``.

``info`` every step: ``state`` (N, 6) = (p in m, q in rad) of {U} in {G}; ``command`` (N, 3);
``measured_command`` (N, 4) = (x, z, yaw, tilt) of the reached probe pose (m, rad);
``reachable`` (N,) bool from the arm; ``cost`` (N,) zeros (no safety constraint in this task).
With a contact force or a force action: ``contact_force`` (N,) N, ``compression_mm`` (N,) under
the image's centre, ``force_cost`` (N,) 1 where the force exceeds ``force_limit``, which is then
also ``cost``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Literal, get_args

import numpy as np
import torch
from gymnasium import spaces

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
from sonogym.geometry import relative_pose, wrap_angle
from sonogym.robots.description import ArmName

ObsMode = Literal["us", "us_heading", "us_memory", "us_scan", "ct", "labels", "state"]
OBS_MODES: tuple[str, ...] = get_args(ObsMode)
#: the modes that keep a memory of the scan (``_init_memory``, ``_observe_with_memory``)
MEMORY_MODES: tuple[str, ...] = ("us_memory", "us_scan")
#: the modes whose observation is a Dict (``observe_tilt`` adds its entry to them)
DICT_MODES: tuple[str, ...] = ("us_heading", *MEMORY_MODES)
#: Along-spine distance (mm) from {G} beyond which an episode ended at another vertebra's view:
#: adjacent lumbar levels lie ~35 mm apart, so 20 mm is past halfway to the next.
LEVEL_MISS_MM = 20.0


@dataclass(frozen=True)
class NavigationConfig(SceneConfig):
    """Navigation task settings (paper defaults). Every field is a ``make_vec`` keyword."""

    obs_modes: ClassVar[tuple[str, ...]] = OBS_MODES

    obs_mode: ObsMode = "us"
    robot: ArmName | None = "kuka_med14"  # probe arm; None: an ideal probe at the command
    goal_yaw: float = math.pi  # rad, transverse image plane
    start_half_extent: float = 0.065  # m: start (x, z) uniform in +-this around {G}
    start_yaw: tuple[float, float] = (1.5, 3.5)  # rad
    workspace_half_extent: float = 0.09  # m: the command is clamped to +-this around {G}
    yaw_range: tuple[float, float] = (math.pi - 2.5, math.pi + 2.5)  # rad, command clamp
    action_scale: tuple[float, float, float] = (0.003, 0.003, 0.1)  # m, m, rad per unit
    action_limit: tuple[float, float, float] = (0.006, 0.006, 0.2)  # m, m, rad per step
    w1: float = 0.045  # reward per mm of position progress (paper)
    memory_lag: int = 30  # control steps: how old us_memory's (us_scan's) remembered image is
    #: add the reached probe's tilt from the vertical, ``tilt`` (2,), to a Dict observation
    observe_tilt: bool = False
    #: a 4th action, the change of the probe's contact force (``contact_force``; 1 N per unit,
    #: at most 2 N per step, kept in [0, 30] N): the tissue under the probe compresses
    force_action: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()  # check_number_fields: memory_lag is an integer
        if self.memory_lag < 1:
            raise ValueError(f"memory_lag must be at least 1 step, got {self.memory_lag}")
        if self.observe_tilt and self.obs_mode not in DICT_MODES:
            raise ValueError(
                f"observe_tilt adds an entry to a Dict observation; obs_mode {self.obs_mode!r} "
                f"has none: use one of {DICT_MODES}, or observe_tilt=False"
            )


def navigation_reward(
    p_before: torch.Tensor,
    q_before: torch.Tensor,
    p_after: torch.Tensor,
    q_after: torch.Tensor,
    w1: float,
) -> torch.Tensor:
    """Paper's reward: w1 (||p_t|| - ||p_t+1||) + ||q_t|| - ||q_t+1||; p in metres (converted to
    mm here, w1 is per mm), q axis-angle in rad. Shapes (N, 3) -> (N,)."""
    dp = (p_before.norm(dim=-1) - p_after.norm(dim=-1)) * 1e3
    return w1 * dp + q_before.norm(dim=-1) - q_after.norm(dim=-1)


def goal_commands(scene: ProbeScene, goal_yaw: float) -> torch.Tensor:
    """(N, 3) {G}'s surface command (x, z, alpha_G) per env: the skin point whose beam (the
    smoothed inward normal) passes through the target vertebra's body centroid
    (``SkinSurface.aim``), so the transverse image at {G} holds the centroid on its centre
    line, at the centroid's level, whatever the trunk's roll or the spine's lean."""
    centres = scene.target_centres_p  # (P, 3) float64
    pid = torch.arange(len(centres), device=centres.device)
    x, z = scene.skin.aim(centres, pid)
    per_patient = torch.stack([x, z, torch.full_like(x, goal_yaw)], -1)
    return per_patient[scene.patient_index].float()


def goal_in_probe(state: torch.Tensor) -> torch.Tensor:
    """The goal's origin seen from the probe, (N, 3) metres in {U}, from ``state`` (N, 6), the
    pose of {U} in {G}: the inverse pose's position, -R_GU^T p."""
    from sonogym.geometry import matrix_from_axis_angle

    p, q = state[:, :3], state[:, 3:]
    return -(matrix_from_axis_angle(q).transpose(-1, -2) @ p.unsqueeze(-1)).squeeze(-1)


def probe_tilt(rot: torch.Tensor) -> torch.Tensor:
    """(N, 2) the probe's tilt from the patient's vertical, from its orientation ``rot``
    (N, 3, 3) in {P} (columns x_U, y_U, z_U): (y_P . x_U, y_P . y_U), the sines of the beam's
    tilt across the image and along the elevation; (0, 0) when the beam points along +y_P
    (into the back of a prone patient). What a tracked probe's orientation (or an IMU on it)
    tells; with the depth of a bone in the image it says how far the beam has drifted
    sideways by then."""
    return rot[:, 1, :2].float()


def navigation_expert(
    state: torch.Tensor,
    gain: float = 0.2,
    action_scale: tuple[float, float, float] = (0.003, 0.003, 0.1),
    action_bound: float = 2.0,
) -> torch.Tensor:
    """Paper's expert a* = rho1 [p.e_x, p.e_y, q.e_z] from the true state.

    ``state`` (N, 6) is the pose of {U} in {G} (``info["state"]``). The goal seen from the probe
    is the inverse pose: position -R_GU^T p and rotation -q; its x_U, y_U components and the
    rotation about z_U, in action units, times ``gain`` (rho1 < 1), clipped to the action box.
    """
    goal_in_u = goal_in_probe(state)
    scale = torch.tensor(action_scale, dtype=state.dtype, device=state.device)
    err = torch.stack([goal_in_u[:, 0], goal_in_u[:, 1], state[:, 5]], -1)
    return (gain * err / scale).clamp(-action_bound, action_bound).float()


class NavigationEnv(TaskEnv):
    """``SonoGym/Navigation-v0`` as a batched env; see the module docstring."""

    def __init__(self, num_envs: int = 1, **kwargs) -> None:
        super().__init__(num_envs, SPEC, kwargs)
        cfg = self.cfg
        # navigation reads the volumes only through the slicer: patients load one at a time
        self.scene = ProbeScene(
            cfg, num_envs, self.device, render=cfg.obs_mode != "state", keep_volumes=False,
            aimed=True,
        )  # fmt: skip
        n = num_envs
        self.goal_cmd = goal_commands(self.scene, cfg.goal_yaw)
        self.goal_pos, self.goal_rot = self.scene.surface_pose(self.goal_cmd)
        self.command = self.goal_cmd.clone()
        self.action_bound = bound = self._set_action_scaling(cfg.action_scale, cfg.action_limit)
        unit_image = spaces.Box(0.0, 1.0, (1, *self.scene.image_shape), np.float32)
        if cfg.obs_mode in MEMORY_MODES:
            self._init_memory()
        obs_space = {
            "us": unit_image,
            "us_heading": spaces.Dict(
                {"image": unit_image, "heading": spaces.Box(-1.0, 1.0, (2,), np.float32)}
            ),
            "us_memory": spaces.Dict(
                {
                    "image": spaces.Box(0.0, 1.0, (2, *self.scene.image_shape), np.float32),
                    "heading": spaces.Box(-1.0, 1.0, (4,), np.float32),
                    "motion": spaces.Box(-np.inf, np.inf, (2,), np.float32),
                }
            ),
            "us_scan": spaces.Dict(
                {
                    "image": spaces.Box(0.0, 1.0, (3, *self.scene.image_shape), np.float32),
                    "heading": spaces.Box(-1.0, 1.0, (6,), np.float32),
                    "motion": spaces.Box(-np.inf, np.inf, (4,), np.float32),
                }
            ),
            "ct": unit_image,
            "labels": spaces.Box(0, 255, (1, *self.scene.image_shape), np.uint8),
            "state": spaces.Box(-np.inf, np.inf, (6,), np.float32),
        }[cfg.obs_mode]
        if cfg.observe_tilt:
            tilt = spaces.Box(-1.0, 1.0, (2,), np.float32)
            obs_space = spaces.Dict({**obs_space.spaces, "tilt": tilt})
        n_act = 3 + cfg.force_action
        self._set_spaces(obs_space, spaces.Box(-bound, bound, (n_act,), np.float32))
        self._state = torch.zeros(n, 6, device=self.device)
        self._prev_state = torch.zeros(n, 6, device=self.device)
        self.scene.randomize_imaging(cfg.imaging_randomization)
        self.scene.release_volumes()

    # ------------------------------------------------------------------ hooks
    def _reset_idx(self, env_ids: torch.Tensor) -> None:
        cfg = self.cfg
        cmd = self.draw_surface_starts(env_ids, self.goal_cmd, cfg.start_half_extent, cfg.start_yaw)
        self.command[env_ids] = cmd
        self.scene.reset(env_ids, cmd)
        self._state[env_ids] = self._measure(env_ids)
        if self.scene.draws_nets:  # last, so the other draws match model-based runs
            self.scene.draw_nets(env_ids, self.rand(len(env_ids)))
        if self.scene.imaging_randomization is not None:  # after: draws above stay the same
            self.scene.draw_imaging(env_ids, self.rand(len(env_ids), 8))

    def _apply_action(self, actions: torch.Tensor) -> None:
        cfg = self.cfg
        if cfg.force_action:
            self.scene.step_force(actions[:, 3])
            actions = actions[:, :3]
        delta = (actions * self.action_scale).clamp(-self.action_limit, self.action_limit)
        rot = self.scene.probe_rot
        # Tangential motion along x_U and y_U, restricted to the frontal (x, z) plane.
        dx = delta[:, 0] * rot[:, 0, 0] + delta[:, 1] * rot[:, 0, 1]
        dz = delta[:, 0] * rot[:, 2, 0] + delta[:, 1] * rot[:, 2, 1]
        w = cfg.workspace_half_extent
        cmd = self.command
        cmd[:, 0] = torch.minimum(
            torch.maximum(cmd[:, 0] + dx, self.goal_cmd[:, 0] - w), self.goal_cmd[:, 0] + w
        )
        cmd[:, 1] = torch.minimum(
            torch.maximum(cmd[:, 1] + dz, self.goal_cmd[:, 1] - w), self.goal_cmd[:, 1] + w
        )
        cmd[:, 2] = (cmd[:, 2] + delta[:, 2]).clamp(*cfg.yaw_range)
        self.scene.step(cmd)
        self._prev_state = self._state.clone()
        self._state = self._measure(None)

    def _measure(self, env_ids: torch.Tensor | None) -> torch.Tensor:
        sl = slice(None) if env_ids is None else env_ids
        p, q = relative_pose(
            self.goal_pos[sl], self.goal_rot[sl], self.scene.probe_pos[sl], self.scene.probe_rot[sl]
        )
        return torch.cat([p, q], -1).float()

    def _get_rewards(self) -> torch.Tensor:
        a, b = self._prev_state, self._state
        return navigation_reward(a[:, :3], a[:, 3:], b[:, :3], b[:, 3:], self.cfg.w1)

    def _get_observations(self, env_ids: torch.Tensor | None):
        mode = self.cfg.obs_mode
        if mode == "state":
            return self._state.clone() if env_ids is None else self._state[env_ids].clone()
        sl = slice(None) if env_ids is None else env_ids
        if mode == "us_heading":
            yaw = self.scene.measured_command(sl)[2]
            heading = torch.stack([torch.cos(yaw), torch.sin(yaw)], -1).float()
            obs = {"image": self.scene.observe("us", env_ids), "heading": heading}
        elif mode in MEMORY_MODES:
            obs = self._observe_with_memory(env_ids)
        else:
            return self.scene.observe(mode, env_ids)
        if self.cfg.observe_tilt:
            obs["tilt"] = probe_tilt(self.scene.probe_rot[sl])
        return obs

    def _init_memory(self) -> None:
        # a ring of memory_lag + 1 slots per env: step t writes slot t % (lag + 1) and reads
        # slot (t - lag) % (lag + 1), which no step since t - lag wrote (the episode's first
        # frame fills every slot), so observing a step twice reads and writes the same
        slots = self.cfg.memory_lag + 1
        n, dev = self.num_envs, self.device
        self._memory_images = torch.zeros(
            n, slots, *self.scene.image_shape, dtype=torch.uint8, device=dev
        )
        self._memory_poses = torch.zeros(n, slots, 3, device=dev)  # reached (x, z, yaw)
        if self.cfg.obs_mode == "us_scan":  # the image and pose where z was lowest
            self._caudal_images = torch.zeros(
                n, *self.scene.image_shape, dtype=torch.uint8, device=dev
            )
            self._caudal_poses = torch.zeros(n, 3, device=dev)

    def _observe_with_memory(self, env_ids: torch.Tensor | None) -> dict[str, torch.Tensor]:
        ids = torch.arange(self.num_envs, device=self.device) if env_ids is None else env_ids
        image = self.scene.observe("us", env_ids)  # (k, 1, H, W)
        x, z, yaw, _ = self.scene.measured_command(slice(None) if env_ids is None else env_ids)
        pose = torch.stack([x, z, yaw], -1).float()
        frame = (image[:, 0].clamp(0, 1) * 255).round().to(torch.uint8)
        lag, slots = self.cfg.memory_lag, self.cfg.memory_lag + 1
        t = self.episode_length_buf[ids]
        first = t == 0
        if bool(first.any()):
            self._memory_images[ids[first]] = frame[first].unsqueeze(1)
            self._memory_poses[ids[first]] = pose[first].unsqueeze(1)
        self._memory_images[ids, t % slots] = frame
        self._memory_poses[ids, t % slots] = pose
        read = (t - lag) % slots
        past = self._memory_images[ids, read].float().unsqueeze(1) / 255
        then = self._memory_poses[ids, read]
        images, poses = [image, past], [pose, then]
        if self.cfg.obs_mode == "us_scan":
            # strictly lower only: observing a step twice leaves the caudal end as it was
            lower = first | (pose[:, 1] < self._caudal_poses[ids, 1])
            if bool(lower.any()):
                self._caudal_images[ids[lower]] = frame[lower]
                self._caudal_poses[ids[lower]] = pose[lower]
            images.append(self._caudal_images[ids].float().unsqueeze(1) / 255)
            poses.append(self._caudal_poses[ids])
        heading = torch.cat([torch.stack([p[:, 2].cos(), p[:, 2].sin()], -1) for p in poses], -1)
        motion = torch.cat([pose[:, :2] - p[:, :2] for p in poses[1:]], -1)
        return {"image": torch.cat(images, 1), "heading": heading.float(), "motion": motion}

    def _get_info(self) -> dict:
        info = {
            "state": self._state.clone(),
            "command": self.command.clone(),
            "measured_command": torch.stack(self.scene.measured_command(), -1).float(),
            "reachable": self.scene.reachable.clone(),
            "cost": torch.zeros(self.num_envs, device=self.device),
            **self.scene.tissue_info(),
        }
        if "force_cost" in info:  # the task's one safety constraint: the force limit
            info["cost"] = info["force_cost"].clone()
        return info

    def goal_offsets(self, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """(N, 3) of the reached probe poses relative to {G}: x and z (m; x across the spine,
        z along it) and wrap(alpha - alpha_G) (rad)."""
        sl = slice(None) if env_ids is None else env_ids
        x, z, yaw, _ = self.scene.measured_command(sl)
        g = self.goal_cmd[sl]
        return torch.stack([x - g[:, 0], z - g[:, 1], wrap_angle(yaw - g[:, 2])], -1)

    def level_miss(self, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """1.0 where the reached probe is more than ``LEVEL_MISS_MM`` from {G} along the spine
        (z), else 0.0."""
        return _level_miss(self.goal_offsets(env_ids))

    def errors(self, env_ids: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Frontal-plane position error (mm) and |wrap(alpha - alpha_G)| (deg) of the reached
        probe poses."""
        return _errors(self.goal_offsets(env_ids))

    def _episode_metrics(self, env_ids: torch.Tensor) -> dict[str, torch.Tensor]:
        offsets = self.goal_offsets(env_ids)
        pos, ang = _errors(offsets)
        miss = _level_miss(offsets)
        return {"position_error_mm": pos, "angle_error_deg": ang, "level_miss": miss}

    def _render_frame(self) -> np.ndarray:
        img = self.scene.observe("us", torch.zeros(1, dtype=torch.long, device=self.device))
        g = (img[0, 0].clamp(0, 1) * 255).to(torch.uint8).cpu().numpy()
        return np.repeat(g[..., None], 3, -1)


def _errors(offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Frontal-plane distance (mm) and |angle| (deg) of ``goal_offsets``."""
    return offsets[:, :2].norm(dim=-1) * 1e3, offsets[:, 2].abs() * 180 / math.pi


def _level_miss(offsets: torch.Tensor) -> torch.Tensor:
    """1.0 where ``goal_offsets`` lie more than ``LEVEL_MISS_MM`` from {G} along the spine."""
    return (offsets[:, 1].abs() * 1e3 > LEVEL_MISS_MM).float()


def make_single(**kwargs) -> SingleEnv:
    """``gymnasium.make("SonoGym/Navigation-v0")``: one env with NumPy I/O."""
    return SingleEnv(NavigationEnv, **kwargs)


def expert(env: NavigationEnv, info: dict) -> torch.Tensor:
    """The paper's expert on ``env`` (``navigation_expert`` from the privileged state); with a
    force action, it holds the force."""
    return hold_force(env, navigation_expert(info["state"], action_scale=env.cfg.action_scale))


SPEC = TaskSpec(
    name="navigation",
    env_id="SonoGym/Navigation-v0",
    # 2: {G} where the beam passes through the target's body centroid (1: straight above it)
    version=2,
    env_cls=NavigationEnv,
    config_cls=NavigationConfig,
    action_names=("dx", "dy", "dalpha"),
    expert=expert,
    expert_label="expert",
    # down to the sacrum first, then the paper's expert: a DAgger expert, not the task's
    experts={"level-counting": "sonogym.envs.level_expert:LevelCountingExpert"},
    metrics=(
        Metric("position_error_mm", "position error", "mm", tolerance=10.0),
        Metric("angle_error_deg", "rotation error", "deg"),
        Metric("level_miss", "level missed", "%", scale=100.0),
    ),
    track=Track(("x", "z", "yaw"), ("mm", "mm", "deg"), probe_track, plane=("x", "z")),
    demo="sonogym.tasks.navigation.demo:DEMO",  # how sonogym demo shows it
    agents="sonogym.tasks.navigation.agents:TRAINING",  # its RL defaults
    memory=EnvMemory(per_env=0.88e6, per_patient=46e6, load_peak=166e6),  # measured, bytes
    dataset="sonogym.tasks.navigation.dataset:DATASET",  # its expert datasets
)
