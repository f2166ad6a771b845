"""Probe held on the skin: surface command -> surface pose -> arm IK -> reached probe pose.

A surface command (x, z, yaw, tilt) names a probe pose on the back's skin (see
``sonogym.anatomy.surface.SkinSurface.surface_pose``: probe face centre on the skin point, beam
along the tilted inward normal). ``SurfaceController`` turns it into the IK target of an arm
whose tool tip is the probe face {U}, runs one control step, and reports the pose the arm
actually reached: the ultrasound image must be sliced from that pose, so tracking lag and
unreachable commands show up in the image.

Robots depend on anatomy, never the other way round.
"""

from __future__ import annotations

import torch

from sonogym.anatomy.surface import SkinSurface
from sonogym.checks import expect_all
from sonogym.robots.arm import Arm, IKResult


class SurfaceController:
    """Keeps a probe arm's probe face on the skin at commanded surface poses.

    Args:
        skin: the patient's back (moved to the arm's device).
        arm: an ``Arm`` whose tool tip is the probe face (e.g. ``ArmConfig(tool=PROBE_TOOL)``)
            and whose base pose is set in the same patient frame.
        settle_steps: control steps ``settle`` runs by default (reference: 200 physics steps
            at 120 Hz = 100 control steps after a reset).
    """

    def __init__(self, skin: SkinSurface, arm: Arm, settle_steps: int = 100) -> None:
        if settle_steps < 1:
            raise ValueError(f"settle_steps must be >= 1, got {settle_steps}")
        self.skin = skin.to(arm.device)
        self.arm = arm
        self.settle_steps = settle_steps

    def _target_pose(self, x, z, yaw, tilt, patient) -> tuple[torch.Tensor, torch.Tensor]:
        """Surface command (N,) each, metres / rad -> probe target pos (N, 3), rot (N, 3, 3);
        see ``step``."""
        n = x.shape[0] if x.dim() == 1 else None
        for name, v in (("x", x), ("z", z), ("yaw", yaw), ("tilt", tilt)):
            if v is None:
                continue
            if n is None or v.dim() != 1 or v.shape[0] != n:
                raise ValueError(
                    "surface command components x, z, yaw, tilt must be 1-D tensors of equal "
                    f"length N; got {name} with shape {tuple(v.shape)} (x: {tuple(x.shape)})"
                )
            expect_all(torch.isfinite(v), f"command component {name} contains NaN or inf")
        dev, dt = self.arm.device, self.arm.dtype
        x, z, yaw = (v.to(dev, dt) for v in (x, z, yaw))
        tilt = None if tilt is None else tilt.to(dev, dt)
        pos, rot = self.skin.surface_pose(x, z, yaw, tilt, patient=patient)
        return pos.to(dt), rot.to(dt)

    def step(
        self,
        q: torch.Tensor,
        x: torch.Tensor,
        z: torch.Tensor,
        yaw: torch.Tensor,
        tilt: torch.Tensor | None = None,
        patient: torch.Tensor | None = None,
        env_ids: torch.Tensor | None = None,
        steps: int = 1,
    ) -> IKResult:
        """``steps`` control steps of joints q (N, 7) toward the surface command x, z, yaw,
        tilt ((N,) each, metres / rad); the result's ``pos`` / ``rot`` are the reached probe
        pose (columns x_U, y_U, z_U). ``patient`` (N,) picks each env's skin when the
        controller holds stacked skins; ``env_ids``: the arms the N rows belong to (None: all;
        see ``Arm.ik_step``)."""
        target_pos, target_rot = self._target_pose(x, z, yaw, tilt, patient)
        return self.arm.track(q, target_pos, target_rot, steps, env_ids)

    def settle(self, q: torch.Tensor, *command, steps: int | None = None, **kw) -> IKResult:
        """``step`` with ``steps`` (default ``settle_steps``) steps toward a fixed command."""
        return self.step(q, *command, steps=steps or self.settle_steps, **kw)

    def skin_distance(
        self, probe_pos: torch.Tensor, patient: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(N,) signed distance of the probe-face centre from the skin along the inward normal,
        metres (positive: inside the body), at the probe's (x, z)."""
        x, z = probe_pos[:, 0], probe_pos[:, 2]
        pt, n = self.skin.point(x, z, patient), self.skin.normal(x, z, patient)
        return ((probe_pos - pt) * n).sum(-1)
