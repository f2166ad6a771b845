"""Bone-surface sensor for the reconstruction task: the bone surface an ultrasound image shows.

The paper (Task 2) assumes a segmentation of the bone surface is available from each 2-D image
and simulates it from the ground truth with a 20 % missing rate per surface point. The sensor
does that on a label image of its own (reference: 50 px wide x 80 px deep at 1 mm, one plane):

1. slice the label map on the probe's image plane at the given (reached) pose;
2. per column (scan line) find the first pixel whose label is any bone
   (``sonogym.anatomy.labels.BONE_IDS``): ultrasound is reflected there and nothing deeper is
   seen, so other bones occlude the target as they do in a real image;
3. keep that pixel only if its label is the target vertebra's (``visible``);
4. drop each kept point independently with probability ``missing_rate`` (``valid``).

Dropout happens after the first-hit search, so a dropped point leaves its scan line empty and
never exposes a deeper surface; a missed segmentation does not make bone transparent. This
differs from the reference implementation, which drops edge pixels first and then takes the
first remaining one per column (a dropped top edge exposes a deeper one), and whose other
vertebrae did not occlude the target (the authors' reference code).

Each point sits at its pixel's centre in the patient frame: origin + row * row_step +
col * col_step (the ``Slicer``'s pixel geometry), metres.

Labels are sampled like the ``Slicer``'s nearest-label lookup (same pixel grid, same result
up to exact ties), but from a label-only copy of each patient (1 byte per voxel instead of the
slicer's 3, no CT interpolation): the sensor runs every step of every env.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from sonogym.anatomy.labels import BONE_IDS
from sonogym.anatomy.patient import Patient
from sonogym.checks import expect_all
from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.ultrasound.slicer import check_poses


@dataclass(frozen=True, eq=False)
class SensedSurface:
    """One sensor reading of N probes (batch-first).

    Attributes:
        points: (N, W, 3) float64 patient-frame position (m) of each scan line's first bone
            pixel (meaningless where ``visible`` is False).
        valid: (N, W) bool, the point is reported (visible and not dropped).
        visible: (N, W) bool, the scan line's first bone pixel belongs to the target
            (before dropout); ``valid`` is a subset of it.
    """

    points: torch.Tensor
    valid: torch.Tensor
    visible: torch.Tensor


class BoneSurfaceSensor:
    """Per-scan-line first bone boundary of a target label, with random misses.

    Args:
        patients: one Patient or a sequence of them (env i uses ``patient_index[i]``).
        width_px, depth_px: image size; the reference's 50 (lateral) x 80 (depth).
        spacing: pixel size, metres (reference: 1 mm), laterally and in depth.
        device: where the label volumes and outputs live.
    """

    def __init__(
        self,
        patients: Patient | Sequence[Patient],
        width_px: int = 50,
        depth_px: int = 80,
        spacing: float = 1e-3,
        device: torch.device | str | None = None,
    ) -> None:
        self.probe = ProbeGeometry(
            depth_px=depth_px,
            width_px=width_px,
            elevation_px=1,
            depth_spacing=spacing,
            width_spacing=spacing,
            elevation_spacing=spacing,
        )
        if isinstance(patients, Patient):
            patients = [patients]
        patients = list(patients)
        if not patients or not all(isinstance(p, Patient) for p in patients):
            raise TypeError("BoneSurfaceSensor needs one Patient or a non-empty sequence of them")
        self.device = torch.device(device) if device is not None else patients[0].labels.device
        labs, offs, dims, orgs, sps = [], [], [], [], []
        off = 0
        for p in patients:
            dx, dy, dz = (d + 2 for d in p.shape)  # a one-voxel air border (label 0)
            lab = torch.zeros((dx, dy, dz), dtype=torch.uint8)
            lab[1:-1, 1:-1, 1:-1] = p.labels.to("cpu")
            labs.append(lab.reshape(-1))
            offs.append(off)
            off += lab.numel()
            dims.append([dx, dy, dz])
            orgs.append(p.origin - p.spacing)  # padded voxel 0
            sps.append(p.spacing)
        if off >= 2**31:
            raise ValueError(f"BoneSurfaceSensor: {off} voxels in all; at most 2**31 fit")
        dev = self.device
        dims_t = torch.tensor(dims, dtype=torch.int64)
        self._lab = torch.cat(labs).to(dev)
        self._offsets = torch.tensor(offs, dtype=torch.int32, device=dev)
        self._dmax = (dims_t - 1).to(dev, torch.float32)  # (P, 3) largest index
        ones = torch.ones(len(dims), dtype=torch.int64)
        strides = torch.stack([dims_t[:, 1] * dims_t[:, 2], dims_t[:, 2], ones], 1)
        self._strides = strides.to(dev, torch.int32)
        self._origin = torch.tensor(np.array(orgs), dtype=torch.float64, device=dev)
        self._spacing = torch.tensor(np.array(sps), dtype=torch.float64, device=dev)
        lut = torch.zeros(256, dtype=torch.bool)
        lut[sorted(BONE_IDS)] = True
        self._bone = lut.to(dev)

    @property
    def nbytes(self) -> int:
        """Bytes held by the sensor's label buffers."""
        return self._lab.numel()

    def labels(
        self, pos: torch.Tensor, rot: torch.Tensor, patient_index: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Nearest labels on the sensor's image plane.

        Returns labels (N, H, W) uint8 and the pixel geometry in {P} (float64, metres):
        origin (N, 3) of pixel (0, 0), row_step (N, 3), col_step (N, 3)."""
        check_poses(pos, rot)
        pr, dev = self.probe, self.device
        n = pos.shape[0]
        pid = torch.as_tensor(patient_index, device=dev).long().reshape(-1)
        if pid.shape[0] != n:
            raise ValueError(f"patient_index must have shape ({n},), got {tuple(pid.shape)}")
        expect_all(
            (pid >= 0) & (pid < len(self._offsets)),
            f"patient_index out of range: the sensor holds {len(self._offsets)}",
        )
        pos = pos.to(dev, torch.float64)
        rot = rot.to(dev, torch.float64)
        xu, zu = rot[..., 0], rot[..., 2]
        origin = pos - (pr.width_px - 1) / 2 * pr.width_spacing * xu
        row_step, col_step = zu * pr.depth_spacing, xu * pr.width_spacing
        sp = self._spacing[pid]
        v0 = ((origin - self._origin[pid]) / sp).float()  # (N, 3) padded voxel coordinates
        dr, dc = (row_step / sp).float(), (col_step / sp).float()
        j = torch.arange(pr.depth_px, device=dev, dtype=torch.float32)
        i = torch.arange(pr.width_px, device=dev, dtype=torch.float32)
        idx = self._offsets[pid].view(n, 1, 1).expand(n, pr.depth_px, pr.width_px).clone()
        for c in range(3):
            v = (v0[:, c, None] + j * dr[:, c, None])[:, :, None] + (i * dc[:, c, None])[:, None]
            v = torch.minimum(v.round_().clamp_(min=0), self._dmax[pid, c].view(n, 1, 1))
            idx += v.to(torch.int32) * self._strides[pid, c].view(n, 1, 1)
        lab = torch.index_select(self._lab, 0, idx.view(-1)).view(n, pr.depth_px, pr.width_px)
        return lab, origin, row_step, col_step

    def sense(
        self,
        pos: torch.Tensor,
        rot: torch.Tensor,
        patient_index: torch.Tensor,
        target_label: int | torch.Tensor,
        generator: torch.Generator | None = None,
        missing_rate: float = 0.2,
    ) -> SensedSurface:
        """Sense the target's bone surface from N probe poses.

        Args:
            pos: (N, 3) probe-face centres in {P}, metres.
            rot: (N, 3, 3) probe orientations (columns x_U, y_U, z_U).
            patient_index: (N,) which patient each probe images.
            target_label: label id of the target vertebra, one int or (N,) ids.
            generator: torch.Generator of the dropout draws (seeded by the env); its device is
                where the uniform draws are made.
            missing_rate: probability that a visible point is dropped, in [0, 1].

        Returns:
            ``SensedSurface`` with points (N, W, 3), valid and visible (N, W).
        """
        if not 0.0 <= missing_rate <= 1.0:
            raise ValueError(f"missing_rate must be in [0, 1], got {missing_rate}")
        lab, origin, row_step, col_step = self.labels(pos, rot, patient_index)
        n, h, w = lab.shape
        bone = self._bone[lab.long()]  # (N, H, W)
        hit = bone.any(1)  # (N, W)
        row = bone.to(torch.uint8).argmax(1)  # first bone row per column (0 where none)
        first = lab.gather(1, row.unsqueeze(1)).squeeze(1)  # (N, W)
        target = torch.as_tensor(target_label, device=lab.device).to(lab.dtype)
        visible = hit & (first == target.reshape(-1, 1) if target.ndim else first == target)
        gen_dev = generator.device if generator is not None else "cpu"
        u = torch.rand((n, w), generator=generator, dtype=torch.float64, device=gen_dev)
        valid = visible & (u.to(lab.device) >= missing_rate)
        col = torch.arange(w, device=lab.device, dtype=torch.float64)
        points = (
            origin[:, None, :]
            + row.to(torch.float64)[..., None] * row_step[:, None, :]
            + col[None, :, None] * col_step[:, None, :]
        )
        return SensedSurface(points, valid, visible)
