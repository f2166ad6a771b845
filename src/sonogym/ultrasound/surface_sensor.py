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
vertebrae did not occlude the target (reference_implementation.md §5).

Each point sits at its pixel's centre in the patient frame: origin + row * row_step +
col * col_step (``Slices`` geometry), metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from sonogym.anatomy.labels import BONE_IDS
from sonogym.anatomy.patient import Patient
from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.ultrasound.slicer import Slicer


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
        # Exact per-pixel nearest-label sampling (no block upsampling): 4000 px per env.
        self.slicer = Slicer(patients, self.probe, device=device, upsample=False)
        self.device = self.slicer.device
        lut = torch.zeros(256, dtype=torch.bool)
        lut[sorted(BONE_IDS)] = True
        self._bone = lut.to(self.device)

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
        s = self.slicer(pos, rot, patient_index)
        lab = s.labels[:, 0]  # (N, H, W)
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
            s.origin[:, 0, None, :]
            + row.to(torch.float64)[..., None] * s.row_step[:, None, :]
            + col[None, :, None] * s.col_step[:, None, :]
        )
        return SensedSurface(points, valid, visible)
