"""Probe geometry: the pixel grid of an ultrasound image (2-D) or volume (3-D) in the probe frame.

Probe frame {U} (docs/design.md): origin at the centre of the probe face, z along the beam into the
body, x along the image's lateral axis, y = elevation. Images are arrays (E, H, W): E elevation
slices, H depth rows (row 0 at the probe face), W lateral columns. Pixel (e, j, i) sits at

    x = (i - (W - 1) / 2) * width_spacing        (lateral, centred)
    y = (e - (E - 1) / 2) * elevation_spacing    (elevation, centred)
    z = j * depth_spacing                        (depth, from the face)

The beams are parallel (a linear array). Every physical quantity of the simulators (attenuation,
PSF width, speckle cell) is defined in metres, so a coarser probe images the same tissue the same
way, only with coarser pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class ProbeGeometry:
    """Size and resolution of one probe's image grid.

    Attributes:
        depth_px: H, rows along the beam (z_U).
        width_px: W, columns along the array (x_U).
        elevation_px: E, slices along the elevation axis (y_U); 1 for a 2-D probe.
        depth_spacing: row spacing, metres.
        width_spacing: column spacing, metres.
        elevation_spacing: slice spacing, metres (unused when elevation_px == 1).
    """

    depth_px: int = 200
    width_px: int = 150
    elevation_px: int = 1
    depth_spacing: float = 0.5e-3  # m
    width_spacing: float = 0.5e-3  # m
    elevation_spacing: float = 0.5e-3  # m

    def __post_init__(self) -> None:
        for name in ("depth_px", "width_px", "elevation_px"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"ProbeGeometry.{name} must be a positive int, got {v!r}")
        for name in ("depth_spacing", "width_spacing", "elevation_spacing"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v < 0.1):
                raise ValueError(
                    f"ProbeGeometry.{name} must be in metres, 0 < {name} < 0.1, got {v!r}"
                )

    # ------------------------------------------------------------ constructors
    @classmethod
    def linear_2d(
        cls, depth_px: int = 200, width_px: int = 150, spacing: float = 0.5e-3
    ) -> ProbeGeometry:
        """The paper's 2-D linear probe: 200 (depth) x 150 (lateral) px at 0.5 mm, i.e. 100 mm
        deep and 75 mm wide."""
        return cls(depth_px, width_px, 1, spacing, spacing, spacing)

    @classmethod
    def volume_3d(
        cls,
        depth_px: int = 50,
        width_px: int = 37,
        elevation_px: int = 5,
        spacing: float = 2e-3,
        elevation_spacing: float = 10e-3,
    ) -> ProbeGeometry:
        """The paper's 3-D volume probe for surgery: 50 (depth) x 37 (lateral) x 5 (elevation)
        at 2 x 2 x 10 mm; the five slices sit at elevation -20, -10, 0, +10, +20 mm."""
        return cls(depth_px, width_px, elevation_px, spacing, spacing, elevation_spacing)

    # ---------------------------------------------------------------- derived
    @property
    def shape(self) -> tuple[int, int, int]:
        """(E, H, W)."""
        return (self.elevation_px, self.depth_px, self.width_px)

    @property
    def depth(self) -> float:
        """Imaged depth, metres (face to the last row's centre plus one row)."""
        return self.depth_px * self.depth_spacing

    @property
    def width(self) -> float:
        """Array width, metres."""
        return self.width_px * self.width_spacing

    def lateral_positions(self, device=None, dtype=torch.float64) -> torch.Tensor:
        """(W,) x_U of each column, metres."""
        i = torch.arange(self.width_px, device=device, dtype=dtype)
        return (i - (self.width_px - 1) / 2) * self.width_spacing

    def depth_positions(self, device=None, dtype=torch.float64) -> torch.Tensor:
        """(H,) z_U of each row, metres."""
        return torch.arange(self.depth_px, device=device, dtype=dtype) * self.depth_spacing

    def elevation_positions(self, device=None, dtype=torch.float64) -> torch.Tensor:
        """(E,) y_U of each slice, metres."""
        e = torch.arange(self.elevation_px, device=device, dtype=dtype)
        return (e - (self.elevation_px - 1) / 2) * self.elevation_spacing
