"""Forward kinematics and Jacobian specialised to an unbranched chain of revolute joints.

pytorch-kinematics parses the URDF and owns the chain's geometry (static offsets, joint axes,
limits); this module only evaluates it faster for the arms we ship. Its generic
``forward_kinematics_tensor`` walks a tree level by level with gathers and scatters, ~100 small
ops for the 11 frames of a KUKA arm with a tool. Here every frame is the previous frame's
child, so the walk is one matmul per frame written in place, and the per-joint rotations are
built for all joints at once. Same formulas in the same order, so the frames and Jacobians are
bit-identical to pytorch-kinematics' on CPU (tests/robots/test_robot_kinematics.py checks it);
for 64 arms on one CPU thread the FK costs ~0.4 ms instead of ~1.5 ms (benchmarks/robots.py).
"""

from __future__ import annotations

import pytorch_kinematics as pk
import torch

_FIXED, _REVOLUTE = 0, 1  # pytorch-kinematics' joint type indices


class SerialChainKinematics:
    """All frame poses and the tip Jacobian of a pytorch-kinematics ``SerialChain`` whose
    frames form one path from the root (frame 0) to the tip (the last frame), with revolute
    and fixed joints only.

    Raises ``ValueError`` for a branched chain or a prismatic joint: use
    ``chain.forward_kinematics_tensor`` for those.
    """

    def __init__(self, chain: pk.SerialChain) -> None:
        parents = chain._direct_parent_idx.tolist()
        types = chain.joint_type_indices.tolist()
        n_frames = len(parents)
        if parents != [-1, *range(n_frames - 1)]:
            raise ValueError(
                "SerialChainKinematics needs an unbranched chain (frame i's parent is frame "
                f"i - 1); got parents {parents}"
            )
        if any(t not in (_FIXED, _REVOLUTE) for t in types) or types[0] != _FIXED:
            raise ValueError(
                "SerialChainKinematics handles revolute and fixed joints below a fixed root; "
                f"got joint types {types} (0 fixed, 1 revolute, 2 prismatic)"
            )
        self.num_frames = n_frames
        self.revolute_frames = [f for f, t in enumerate(types) if t == _REVOLUTE]
        if not self.revolute_frames:
            raise ValueError("SerialChainKinematics needs at least one revolute joint")
        joint_of_frame = chain._joint_indices_clamped.tolist()
        n_joints = len(self.revolute_frames)
        if [joint_of_frame[f] for f in self.revolute_frames] != list(range(n_joints)):
            raise ValueError("joint order differs from frame order along the chain")
        offsets = chain._static_offsets
        self._offsets = offsets  # (F, 4, 4): link offset @ joint offset per frame
        self._rev_offsets = offsets[self.revolute_frames].contiguous()  # (J, 4, 4)
        axes = chain.axes  # (J, 3) unit axes in each joint's frame
        self._axes = axes
        kx, ky, kz = axes.unbind(-1)
        zero = torch.zeros_like(kx)
        # cross-product matrix [k]x and k k^T per joint: R = c I + s [k]x + (1 - c) k k^T,
        # which is pytorch-kinematics' axis_and_angle_to_matrix_33 term for term
        self._skew = torch.stack(
            [
                torch.stack([zero, -kz, ky], -1),
                torch.stack([kz, zero, -kx], -1),
                torch.stack([-ky, kx, zero], -1),
            ],
            -2,
        )
        self._outer = axes.unsqueeze(-1) * axes.unsqueeze(-2)
        self._eye3 = torch.eye(3, dtype=axes.dtype, device=axes.device)
        self._dof_frames = slice(self.revolute_frames[0], self.revolute_frames[-1] + 1)
        if list(range(n_frames))[self._dof_frames] != self.revolute_frames:
            raise ValueError("SerialChainKinematics needs the revolute joints consecutive")

    def frames(self, q: torch.Tensor) -> torch.Tensor:
        """(F, N, 4, 4) pose of every frame in the chain's root frame at joints ``q`` (N, J),
        in pytorch-kinematics' frame order (``chain.frame_to_idx``)."""
        n = q.shape[0]
        c = torch.cos(q)[..., None, None]
        s = torch.sin(q)[..., None, None]
        joint = q.new_zeros(n, q.shape[1], 4, 4)
        joint[..., :3, :3] = c * self._eye3 + s * self._skew + (1 - c) * self._outer
        joint[..., 3, 3] = 1
        local = self._rev_offsets @ joint  # (N, J, 4, 4)
        out = q.new_empty(self.num_frames, n, 4, 4)
        out[0] = self._offsets[0]
        for k, f in enumerate(self.revolute_frames):
            torch.matmul(out[f - 1], local[:, k], out=out[f])
        for f in range(self.revolute_frames[-1] + 1, self.num_frames):
            torch.matmul(out[f - 1], self._offsets[f], out=out[f])
        return out

    def jacobian(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, 6, J) geometric Jacobian of the tip (the last frame) in the root frame, rows
        (linear velocity, angular velocity), from ``frames`` as returned by ``frames``."""
        dof = frames[self._dof_frames]  # (J, N, 4, 4)
        z = torch.einsum("nbij,nj->nbi", dof[..., :3, :3], self._axes)  # joint axes in the root
        dp = frames[-1, :, :3, 3].unsqueeze(0) - dof[..., :3, 3]
        return torch.cat([torch.cross(z, dp, dim=2), z], dim=2).permute(1, 2, 0)
