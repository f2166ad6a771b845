"""Batched rotation and pose helpers (torch). Quaternions are (w, x, y, z); poses are 4x4.

Shared by every layer, so it imports nothing from sonogym.
"""

from __future__ import annotations

import math

import torch


def normalize(v: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit vectors along the last axis."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)


def wrap_angle(a: torch.Tensor) -> torch.Tensor:
    """Wrap angles to [-pi, pi)."""
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


# Every formula's terms, as one (..., 10) vector read from the flat (row-major) matrix:
# [1 + t, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22,
#  m21 - m12, m02 - m20, m10 - m01, m01 + m10, m02 + m20, m12 + m21]. They fill a symmetric
# 4x4 whose row k is 4 q_k (w, x, y, z): formula k normalises row k.
_CANDIDATE_TERMS = ((0, 4, 5, 6), (4, 1, 7, 8), (5, 7, 2, 9), (6, 8, 9, 3))
_QUAT_CONSTANTS: dict = {}


def _quat_constants(device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    """Index and sign tensors of ``quat_from_matrix``, made once per device and dtype."""
    key = (device, dtype)
    if key not in _QUAT_CONSTANTS:
        long = {"dtype": torch.long, "device": device}
        _QUAT_CONSTANTS[key] = (
            torch.tensor([7, 2, 3, 1, 2, 5], **long),  # first operands of the off-diagonals
            torch.tensor([5, 6, 1, 3, 6, 7], **long),  # second operands
            torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0], dtype=dtype, device=device),  # - or +
            torch.tensor(_CANDIDATE_TERMS, **long),
        )
    return _QUAT_CONSTANTS[key]


def quat_from_matrix(r: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w >= 0.

    Of the four standard formulas (dividing by 4|w|, 4|x|, 4|y| or 4|z|), each matrix uses
    the one with the largest denominator. The formulas are batched: a dozen tensor ops
    instead of ~60, as op overhead dominates at tens of matrices per call."""
    first, second, sign, candidate = _quat_constants(r.device, r.dtype)
    m = r.reshape(*r.shape[:-2], 9)
    m00, m11, m22 = m[..., 0:1], m[..., 4:5], m[..., 8:9]
    t = (m00 + m11) + m22
    one_minus_m00 = 1 - m00
    diag = torch.cat(
        [1 + t, ((1 + m00) - m11) - m22, (one_minus_m00 + m11) - m22, (one_minus_m00 - m11) + m22],
        -1,
    )
    off = m.index_select(-1, first) + sign * m.index_select(-1, second)
    terms = torch.cat([diag, off], -1)
    q = normalize(torch.gather(terms, -1, candidate[diag.argmax(-1)]))
    return torch.where(q[..., :1] < 0, -q, q)


def matrix_from_quat(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions (w, x, y, z) -> (..., 3, 3) rotation matrices."""
    w, x, y, z = normalize(q).unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_from_axis_angle(v: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors (axis * angle, rad) -> (..., 3, 3) matrices (Rodrigues)."""
    angle = v.norm(dim=-1, keepdim=True)
    axis = v / angle.clamp_min(1e-12)
    x, y, z = axis.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )
    s = torch.sin(angle)[..., None]
    c = torch.cos(angle)[..., None]
    eye = torch.eye(3, dtype=v.dtype, device=v.device).expand(k.shape)
    return eye + s * k + (1 - c) * (k @ k)


def axis_angle_from_matrix(r: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) rotation vectors with angle in [0, pi]."""
    q = quat_from_matrix(r)
    vec = q[..., 1:]
    s = vec.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., :1])
    # angle/sin(angle/2) -> 2 as angle -> 0
    scale = torch.where(s > 1e-8, angle / s.clamp_min(1e-12), torch.full_like(s, 2.0))
    return vec * scale


def in_frame(
    frame_pos: torch.Tensor,
    frame_rot: torch.Tensor,
    pos: torch.Tensor,
    rot: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Express a pose given in a parent frame in the frame F = (frame_pos, frame_rot), both in
    that parent: position R_F^T (pos - frame_pos) (..., 3) and rotation R_F^T rot (..., 3, 3)
    (None when ``rot`` is None)."""
    rf_t = frame_rot.transpose(-1, -2)
    p = (rf_t @ (pos - frame_pos).unsqueeze(-1)).squeeze(-1)
    return p, (None if rot is None else rf_t @ rot)


def relative_pose(
    frame_pos: torch.Tensor, frame_rot: torch.Tensor, pos: torch.Tensor, rot: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pose of a body in the frame F: position (..., 3) and axis-angle (..., 3)."""
    p, r = in_frame(frame_pos, frame_rot, pos, rot)
    return p, axis_angle_from_matrix(r)


def make_pose(rot: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation and (..., 3) position -> (..., 4, 4) homogeneous pose."""
    pose = torch.zeros(*pos.shape[:-1], 4, 4, dtype=pos.dtype, device=pos.device)
    pose[..., :3, :3] = rot
    pose[..., :3, 3] = pos
    pose[..., 3, 3] = 1
    return pose


def invert_pose(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of (..., 4, 4) rigid poses."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    return make_pose(rot_t, -(rot_t @ pose[..., :3, 3:4]).squeeze(-1))


def rot_x(a: torch.Tensor) -> torch.Tensor:
    """(...,) angles -> (..., 3, 3) rotations about x."""
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack(
        [torch.stack([o, z, z], -1), torch.stack([z, c, -s], -1), torch.stack([z, s, c], -1)], -2
    )


def rot_y(a: torch.Tensor) -> torch.Tensor:
    """(...,) angles -> (..., 3, 3) rotations about y."""
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack(
        [torch.stack([c, z, s], -1), torch.stack([z, o, z], -1), torch.stack([-s, z, c], -1)], -2
    )


def rot_z(a: torch.Tensor) -> torch.Tensor:
    """(...,) angles -> (..., 3, 3) rotations about z."""
    c, s, o, z = torch.cos(a), torch.sin(a), torch.ones_like(a), torch.zeros_like(a)
    return torch.stack(
        [torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1), torch.stack([z, z, o], -1)], -2
    )
