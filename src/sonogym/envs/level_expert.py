"""Navigation's level-counting expert: down to the sacrum first, then up to {G}.

A sonographer finds L4 by counting levels up from the sacrum. ``LevelCountingExpert`` does the
same from the privileged state: in phase 1 it drives the probe caudally, transverse (yaw pi)
and over the goal's x, until the reached probe's z is at or below the **caudal waypoint**;
in phase 2 it is the paper's expert toward {G} (``navigation_expert``). The waypoint is the
skin point aimed (``SkinSurface.aim``) at one level below L5's body centroid,
c_L5 + (c_L5 - c_L4), over the sacrum; where the patient has no L5 frame it has none and the
expert goes straight to {G}, as it does from a start already at or below the waypoint.

Phase 1 is the paper's expert toward the surface pose (x_G, z_W - ``overshoot``, pi): the
same gain, action scaling and clipping, aimed ``overshoot`` below the waypoint so that the
probe passes it at speed instead of creeping up to it. Where that aim lies outside the
workspace (the command is clamped to ``workspace_half_extent`` of {G}), the waypoint is
raised to ``overshoot`` inside the workspace's caudal edge, so that phase 1 always ends.

Why it exists: a policy observing ``us_scan`` can only learn to count levels if it is shown
trajectories that visit the sacrum; the paper's expert, driving straight to {G}, never goes
below L4 from a cranial start. It is a DAgger expert (``sonogym train --dagger-expert
level-counting``), not the task's expert: ``SPEC.expert`` stays the paper's.

Per-env state: whether the episode has reached the waypoint (``reached``), cleared by
``reset(env_mask)`` at each env's episode start and updated from ``info`` at every ``act``, so
the same expert labels any visited trajectory (its own, a learner's, a mixture's).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from sonogym.anatomy.landmarks import LandmarkError
from sonogym.envs.navigation import NavigationEnv, navigation_expert
from sonogym.envs.probe_scene import hold_force
from sonogym.geometry import matrix_from_axis_angle, relative_pose


def caudal_waypoints(scene) -> torch.Tensor:
    """(P,) z (m, {P}) of each patient's caudal waypoint: the skin point whose beam passes
    through c_L5 + (c_L5 - c_L4) (one level below L5's body centroid); -inf where the patient
    has no L4 or L5 frame."""
    below, have = [], []
    for patient in scene.patients:
        try:
            c4 = patient.landmarks.vertebra("L4").centre
            c5 = patient.landmarks.vertebra("L5").centre
        except LandmarkError:
            below.append(np.zeros(3))
            have.append(False)
            continue
        below.append(2 * np.asarray(c5) - np.asarray(c4))
        have.append(True)
    dev = scene.device
    target = torch.tensor(np.array(below), dtype=torch.float64, device=dev)
    _, z = scene.skin.aim(target, torch.arange(len(below), device=dev))
    have_t = torch.tensor(have, device=dev)
    return torch.where(have_t, z, torch.full_like(z, -math.inf))


class LevelCountingExpert:
    """A ``Policy`` on a ``NavigationEnv``: the paper's expert toward a caudal waypoint until
    the episode has reached it, then toward {G} (module docstring).

    Args:
        env: the navigation env (its scene's patients, goal and workspace).
        overshoot: m, phase 1 aims this far below the waypoint (and the waypoint stays this far
            inside the workspace's caudal edge).
        gain, action_bound: the paper's expert's (``navigation_expert``).
    """

    def __init__(
        self, env, overshoot: float = 0.005, gain: float = 0.2, action_bound: float = 2.0
    ) -> None:
        if not isinstance(env.unwrapped, NavigationEnv):
            raise TypeError(
                f"the level-counting expert drives a navigation env, got {type(env).__name__}"
            )
        env = env.unwrapped
        if not overshoot > 0:
            raise ValueError(f"overshoot must be > 0 m, got {overshoot}")
        self.env = env
        self.gain, self.action_bound = float(gain), float(action_bound)
        scene, goal = env.scene, env.goal_cmd
        edge = goal[:, 1] - env.cfg.workspace_half_extent + overshoot
        z_w = caudal_waypoints(scene)[scene.patient_index].float()
        #: (N,) z (m) each env's episode must reach before heading for {G}; -inf: none
        self.waypoint_z = torch.where(torch.isfinite(z_w), torch.maximum(z_w, edge), z_w)
        aim_z = torch.where(torch.isfinite(z_w), self.waypoint_z - overshoot, goal[:, 1])
        aim = torch.stack([goal[:, 0], aim_z, goal[:, 2]], -1)
        self._aim_pos, self._aim_rot = scene.surface_pose(aim)
        #: (N,) bool: the episode has reached its waypoint (or has none)
        self.reached = torch.zeros(env.num_envs, dtype=torch.bool, device=env.device)

    def reset(self, env_mask: torch.Tensor | None = None) -> None:
        """Forget the waypoint for the envs in ``env_mask`` (None: every env)."""
        if env_mask is None:
            self.reached.zero_()
        else:
            self.reached &= ~torch.as_tensor(env_mask, device=self.reached.device).bool()

    def act(self, obs, info) -> torch.Tensor:
        """(N, 3) actions from ``info``'s ``state`` and ``measured_command`` (the reached z);
        with a force action (N, 4), the force held."""
        state = info["state"]
        self.reached |= info["measured_command"][:, 1] <= self.waypoint_z
        to_goal = self._expert(state)
        to_aim = self._expert(self._state_in_aim(state))
        return hold_force(self.env, torch.where(self.reached.unsqueeze(-1), to_goal, to_aim))

    def _expert(self, state: torch.Tensor) -> torch.Tensor:
        scale = self.env.cfg.action_scale
        return navigation_expert(state, self.gain, scale, self.action_bound)

    def _state_in_aim(self, state: torch.Tensor) -> torch.Tensor:
        """The pose of {U} in phase 1's aim frame (N, 6), from its pose in {G}."""
        env = self.env
        g_pos, g_rot = env.goal_pos, env.goal_rot
        rot_gu = matrix_from_axis_angle(state[:, 3:].to(g_rot.dtype))
        pos = g_pos + (g_rot @ state[:, :3].to(g_pos.dtype).unsqueeze(-1)).squeeze(-1)
        p, q = relative_pose(self._aim_pos, self._aim_rot, pos, g_rot @ rot_gu)
        return torch.cat([p, q], -1).float()
