"""Tools held by the arms: the ultrasound probe and the surgical drill, with their tip frames.

A tool is rigidly mounted on an arm's flange; its tip frame is a fixed pose in the flange frame
(the flange frame's z points out of the flange). The tip is the frame the arm controls:

* probe: the probe frame {U} (docs/design.md): origin at the centre of the probe face, x_U along
  the transducer array (image lateral axis), y_U elevation, z_U along the beam into the body;
* drill: the drill-tip frame {D}: origin at the tip of the bit, z_D along the drill axis,
  pointing out of the tool (into the bone).

The tools' geometry for viewers lives in ``urdf/probe_tool.urdf`` and ``urdf/drill_tool.urdf``;
the offsets below are what the kinematics use (``description.assemble_urdf`` writes them into
the tip joint), so they can be changed without editing any file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from sonogym.geometry import make_pose, matrix_from_axis_angle


@dataclass(frozen=True)
class ToolConfig:
    """A flange-mounted tool and its tip frame.

    Attributes:
        urdf: file name of the tool description in ``sonogym/robots/urdf``.
        mount_link: the tool's root link, attached to the flange with the flange's pose.
        tip_link: the tip frame's link (the frame the arm controls).
        tip_joint: the fixed joint mount_link -> tip_link whose origin the config overrides.
        tip_pos: tip origin in the flange frame, metres.
        tip_rotvec: tip orientation in the flange frame as a rotation vector (axis * angle), rad.
    """

    urdf: str
    mount_link: str
    tip_link: str
    tip_joint: str
    tip_pos: tuple[float, float, float]  # m, in the flange frame
    tip_rotvec: tuple[float, float, float] = (0.0, 0.0, 0.0)  # rad, rotation vector

    @classmethod
    def shipped(
        cls, name: str, tip_link: str, tip_pos: tuple[float, float, float],
        tip_rotvec: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> ToolConfig:  # fmt: skip
        """A tool whose description ships as ``<name>_tool.urdf``: root link
        ``<name>_mount``, tip ``tip_link`` on the fixed joint ``<tip_link>_joint``."""
        urdf, mount, joint = f"{name}_tool.urdf", f"{name}_mount", f"{tip_link}_joint"
        return cls(urdf, mount, tip_link, joint, tip_pos, tip_rotvec)

    def __post_init__(self) -> None:
        for name in ("tip_pos", "tip_rotvec"):
            v = getattr(self, name)
            if len(v) != 3 or not all(math.isfinite(float(c)) for c in v):
                raise ValueError(f"ToolConfig.{name} must be 3 finite numbers, got {v!r}")

    @property
    def tip_rpy(self) -> tuple[float, float, float]:
        """Tip orientation as URDF roll-pitch-yaw (R = Rz(yaw) Ry(pitch) Rx(roll)), rad."""
        rpy = Rotation.from_rotvec(np.asarray(self.tip_rotvec, dtype=np.float64)).as_euler("xyz")
        return (float(rpy[0]), float(rpy[1]), float(rpy[2]))

    def tip_pose(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
    ) -> torch.Tensor:
        """(4, 4) pose of the tip frame in the flange frame (metres)."""
        rot = matrix_from_axis_angle(torch.tensor(self.tip_rotvec, dtype=torch.float64))
        return make_pose(rot, torch.tensor(self.tip_pos, dtype=torch.float64)).to(device, dtype)


#: Ultrasound probe: probe face {U} 0.13 m along the flange's z (reference: the end-effector
#: frame is 0.13 m from the probe face along the beam axis), x_U/y_U parallel to the flange's x/y.
PROBE_TOOL = ToolConfig.shipped("probe", "probe_face", (0.0, 0.0, 0.13))

#: Surgical drill: drill tip {D} 0.135 m along the flange's z, z_D along the flange's z. The
#: reference writes the same tip as (its drill body) o (translation (0, 0, -0.135) m, 180 deg
#: about y) because that body's z points back toward the arm; ours points out of the flange.
DRILL_TOOL = ToolConfig.shipped("drill", "drill_tip", (0.0, 0.0, 0.135))
