"""Where the arms stand relative to the patient: base poses in the patient frame {P}.

The reference implementation places its robots in an IsaacLab world frame {W} (z up) and the
patient by the pose of its voxel frame {H} (array axes x, y, z scaled by 1.5 mm; y grows from
the back toward the front, so the back's skin is at the smallest y):

    p_W = R_WH p_H + t_WH,   R_WH = scipy euler("yxz", (-90, -90, 0) deg) = [[0, 0, -1],
                                                                            [1, 0,  0],
                                                                            [0, -1, 0]]

i.e. x_H -> +y_W, y_H (anterior) -> -z_W (down: the patient lies prone, back up), z_H -> -x_W.
Taking {H} as our {P} up to a translation (the reference reads arrays in TotalSegmentator's
RAS-like layout), a base at p_W with the identity orientation sits in {P} at
R_WH^T (p_W - t_WH) with axes x_base = -z_P, y_base = +x_P, z_base = -y_P (up).
``reference_base_in_voxel_frame`` does that conversion:

=================  =====================  ======================  =========================
scene              base in {W}, m          patient t_WH, m         base in {H}, m
=================  =====================  ======================  =========================
navigation probe   (0, -0.75, 0.5)        (0.2, -0.45, 1.0)       (-0.30, 0.50, 0.20)
surgery probe      (0, -0.5, 0.0) (FR3)   (0.2, -0.2, 0.7)        (-0.30, 0.70, 0.20)
surgery drill      (0, 0.5, 0.1) (KUKA)   (0.2, -0.2, 0.7)        (0.70, 0.60, 0.20)
=================  =====================  ======================  =========================

{H}'s origin is the corner of the reference's CT crop, which we do not have, so these numbers
only fix the base *relative to the target vertebra*: the guidance command range centres L4 at
about x_H = 0.21-0.23 m, z_H = 0.20-0.26 m, and the back's skin lies a few centimetres below
y_H = 0. Hence every placement here is an offset from an **anchor**, the skin point above the
target vertebra's centre (x_v, h(x_v, z_v), z_v), so it follows each patient's anatomy, plus
an initial joint configuration that suits it (the arm settles from there to its first target).
All keep the reference's base heading (x_base = -z_P, y_base = +x_P, z_base up).

* Navigation / reconstruction probe arm (KUKA), ``NAVIGATION_PROBE_BASE``: 0.42 m toward the
  patient's left (-x_P), 0.50 m below the skin, level with the vertebra; close to the
  reference's offsets (about 0.52 m left, 0.44 m below), with the upper arm nearly vertical,
  the forearm sloping down over the patient and the wrist (A6 about 1.7 rad) far from its
  singularity, so that tracking is smooth. From its initial joints it reaches, with every
  joint at least 0.2 rad inside its limits, the whole navigation workspace: probe face on the
  skin within +-80 mm in x and +-100 mm in z around the vertebra, beam along the normal, yaw
  in [1.5, 3.5] rad; with tilt +-0.25 rad over the same area, and +-0.4 rad within +-40 mm in x
  and +-50 mm in z (the reconstruction task's region around its vertebra), at least 0.05 rad
  inside the limits (tested). Some poses tilted 0.4 rad toward or away from the robot at the
  workspace's x edges are out of reach (about 4 % of a test set with half its poses on the
  edges; each missed by < 1 mm and reported unreachable): with the probe face 0.256 m from
  the wrist centre (0.126 m flange + 0.13 m probe) the elbow (A4, +-120 deg) and the wrist
  (A6, +-120 deg) must span a wide range of wrist positions and directions, and in a search
  over base positions beside the bed no base that kept A6 away from zero reached them all.
* ``OVERHEAD_PROBE_BASE`` (KUKA): 0.45 m to the patient's left with the base 0.25 m *above* the
  skin (a pedestal; upper arm reaching over the patient, forearm pointing down). It reaches the
  full navigation workspace with tilt +-0.4 rad everywhere (joints >= 0.1 rad inside their
  limits, tested), but its wrist works near A6 = 0, where holding the probe's orientation
  needs fast A5/A7/A6 motion: at 3 mm per control step (0.18 m/s) it lags by up to about 8 mm
  where the default placement lags by < 1 mm.
* Surgery probe arm (FR3): the reference's offsets, 0.52 m to the patient's left and 0.64 m
  below the skin; the FR3 reaches the surgery probe poses (probe 20-55 mm left of the midline,
  tilted 0.25-0.55 rad toward it) with wide joint margins.
* Surgery drill arm (KUKA): 0.70 m to the patient's right, 0.30 m below the skin (reference:
  about 0.48 m right, 0.54 m below, from which drill-tip poses along a pedicle trajectory
  from 170 mm above the target down to the target keep the elbow or wrist at a limit); the tip
  then reaches the whole drilling corridor with every joint about 0.3 rad inside its limits
  (tested).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from sonogym.geometry import make_pose, rot_z

#: The reference's patient orientation: scipy euler sequence and angles (deg) of {H} in {W}.
REFERENCE_PATIENT_EULER = ("yxz", (-90.0, -90.0, 0.0))

#: Rotation from the reference's world {W} to {P}: R_PW = R_WH^T (columns: W's axes in {P}).
_R_PW = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])


def reference_patient_rotation() -> np.ndarray:
    """(3, 3) R_WH: the reference patient's voxel frame axes in its world frame."""
    seq, angles = REFERENCE_PATIENT_EULER
    return Rotation.from_euler(seq, angles, degrees=True).as_matrix()


def reference_base_in_voxel_frame(
    base_pos_world: tuple[float, float, float], patient_pos_world: tuple[float, float, float]
) -> np.ndarray:
    """(4, 4) pose in the reference's voxel frame {H} of a robot base at ``base_pos_world``
    (identity orientation, as the reference spawns it) when the patient's {H} origin is at
    ``patient_pos_world`` with the reference's orientation. Metres."""
    r_wh = reference_patient_rotation()
    pose = np.eye(4)
    pose[:3, :3] = r_wh.T
    pose[:3, 3] = r_wh.T @ (np.asarray(base_pos_world) - np.asarray(patient_pos_world))
    return pose


@dataclass(frozen=True)
class BasePlacement:
    """A robot base relative to the anchor (the skin point above the target vertebra).

    Attributes:
        offset: base origin minus anchor, in {P}, metres (+x patient's right, +y anterior,
            i.e. below the skin of a prone patient, +z superior).
        init_joints: initial joint configuration that suits this placement, rad.
        heading: rotation of the base about the room's vertical (-y_P), rad; 0 gives the
            reference's orientation x_base = -z_P, y_base = +x_P, z_base = -y_P (up).
    """

    offset: tuple[float, float, float]  # m, in {P}
    init_joints: tuple[float, ...]  # rad
    heading: float = 0.0  # rad, about the vertical

    def __post_init__(self) -> None:
        if len(self.offset) != 3 or not all(math.isfinite(c) for c in self.offset):
            raise ValueError(f"BasePlacement.offset must be 3 finite numbers, got {self.offset}")
        if not all(math.isfinite(q) for q in self.init_joints):
            raise ValueError(f"BasePlacement.init_joints must be finite, got {self.init_joints}")
        if not math.isfinite(self.heading):
            raise ValueError(f"BasePlacement.heading must be finite, got {self.heading}")

    def rotation(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(3, 3) base orientation in {P} (columns: the base's axes)."""
        r_pw = torch.tensor(_R_PW, dtype=torch.float64)
        return (r_pw @ rot_z(torch.tensor(self.heading, dtype=torch.float64))).to(dtype)

    def base_pose(self, anchor: torch.Tensor) -> torch.Tensor:
        """Base pose(s) in {P}: anchor (3,) -> (4, 4), or (N, 3) -> (N, 4, 4); metres."""
        anchor = torch.as_tensor(anchor)
        if anchor.shape[-1] != 3 or anchor.dim() not in (1, 2):
            raise ValueError(f"anchor must be (3,) or (N, 3), got {tuple(anchor.shape)}")
        if not bool(torch.isfinite(anchor).all()):
            raise ValueError("anchor contains NaN or inf")
        dtype = anchor.dtype if anchor.is_floating_point() else torch.float32
        offset = torch.tensor(self.offset, dtype=dtype, device=anchor.device)
        rot = self.rotation(dtype).to(anchor.device).expand(*anchor.shape[:-1], 3, 3)
        return make_pose(rot, anchor.to(dtype) + offset)


#: KUKA probe arm of the navigation and reconstruction tasks (initial probe pose: about 60 mm
#: above the anchor, beam along the normal, yaw 2.5 rad).
NAVIGATION_PROBE_BASE = BasePlacement(
    offset=(-0.42, 0.50, 0.0), init_joints=(1.57, 0.05, 0.0, -1.43, 0.0, 1.66, 0.64)
)
#: KUKA probe arm on a pedestal above the skin: reaches tilts of +-0.4 rad over the whole
#: navigation workspace, at the cost of slower tracking (see the module docstring).
OVERHEAD_PROBE_BASE = BasePlacement(
    offset=(-0.45, -0.25, 0.0), init_joints=(1.59, 1.32, -0.03, -1.71, 0.24, 0.11, 0.42)
)
#: FR3 probe arm of the surgery task (initial probe pose: about 50 mm above the skin 40 mm left
#: of the anchor, tilted 0.4 rad toward the midline, image plane sagittal).
SURGERY_PROBE_BASE = BasePlacement(
    offset=(-0.52, 0.64, 0.0), init_joints=(1.51, -0.42, 0.04, -1.63, 0.02, 1.65, -1.59)
)
#: KUKA drill arm of the surgery task (initial tip pose: on a 15 deg medial right-pedicle
#: trajectory, 140 mm before a target 100 mm below the anchor).
SURGERY_DRILL_BASE = BasePlacement(
    offset=(0.70, 0.30, 0.0), init_joints=(-0.88, 0.87, -1.27, -1.39, -2.17, -1.24, -0.57)
)
