"""The back's skin: height map, smoothed inward normals, and the surface pose of a probe.

The skin over the back is the surface y = h(x, z) (the patient lies prone; y is anterior, so the
back is the smallest-y body surface). ``SkinSurface`` stores h on the patient's (x, z) voxel grid
with sub-voxel accuracy and answers batched bilinear queries at any (x, z) in metres.

Surface command (docs/design.md): (x, z, yaw, tilt) ->
  * z_U0 = inward normal n(x, z) (smoothed, so a 75 mm probe face sees a stable direction);
  * x_U = the tangent vector whose frontal-plane (x-z) projection points along
    (cos yaw, 0, sin yaw): yaw is exactly the angle of the probe's lateral axis in the frontal
    plane, from +x_P toward +z_P (docs/design.md), whatever the skin's slope;
  * y_U0 = z_U0 x x_U;
  * tilt rotates about x_U: y_U = y_U0 cos t + z_U0 sin t, z_U = z_U0 cos t - y_U0 sin t;
  * the probe-face centre sits on the skin point (x, h(x, z), z).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage

from sonogym.anatomy.volume import Volume
from sonogym.geometry import normalize

#: HU halfway between air (-1000) and soft tissue (~0): where the skin crosses.
SKIN_HU_THRESHOLD = -500.0


class SkinSurface:
    """Batched queries of the back's skin surface.

    Args:
        height: (NX, NZ) skin y in metres at grid nodes x0 + i*dx, z0 + k*dz.
        x0, z0: grid origin, metres.
        dx, dz: grid spacing, metres.
        normal_sigma: Gaussian smoothing (metres) of the height map before normals are taken.
    """

    def __init__(
        self,
        height: torch.Tensor | np.ndarray,
        x0: float,
        z0: float,
        dx: float,
        dz: float,
        normal_sigma: float = 0.008,
    ) -> None:
        h = np.asarray(height, dtype=np.float64)
        if h.ndim != 2 or min(h.shape) < 2:
            raise ValueError(f"height map must be 2-D with at least 2x2 nodes, got {h.shape}")
        if not np.isfinite(h).all():
            raise ValueError("height map has NaN/inf; fill columns without skin first")
        self.x0, self.z0, self.dx, self.dz = float(x0), float(z0), float(dx), float(dz)
        self.normal_sigma = float(normal_sigma)
        hs = ndimage.gaussian_filter(h, (normal_sigma / dx, normal_sigma / dz), mode="nearest")
        dh_dx, dh_dz = np.gradient(hs, dx, dz)
        n = np.stack([-dh_dx, np.ones_like(hs), -dh_dz], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        # (P, NX, NZ, 4): height + inward normal, so one gather serves both queries; P patients
        # (one here, several after ``stack``), each with its own grid in ``_grid``.
        self._table = torch.from_numpy(np.concatenate([h[..., None], n], -1)).float()[None]
        self._grid = torch.tensor([[x0, z0, dx, dz, h.shape[0], h.shape[1]]], dtype=torch.float64)

    @classmethod
    def stack(cls, surfaces: list[SkinSurface]) -> SkinSurface:
        """One surface object answering for several patients: queries take ``patient`` (an
        index tensor broadcastable to the query) to pick whose skin to use. Single-patient
        surfaces on the same device afterwards read their rows of the stacked table."""
        if not surfaces:
            raise ValueError("stack needs at least one SkinSurface")
        tables = [t for s in surfaces for t in s._table]
        nx = max(t.shape[0] for t in tables)
        nz = max(t.shape[1] for t in tables)
        padded = []
        for t in tables:  # pad by edge replication (never read: lookups clamp to each grid)
            t = torch.cat([t, t[-1:].expand(nx - t.shape[0], -1, -1)], 0)
            padded.append(torch.cat([t, t[:, -1:].expand(-1, nz - t.shape[1], -1)], 1))
        out = cls.__new__(cls)
        out.x0, out.z0, out.dx, out.dz = (
            surfaces[0].x0,
            surfaces[0].z0,
            surfaces[0].dx,
            surfaces[0].dz,
        )
        out.normal_sigma = surfaces[0].normal_sigma
        out._table = torch.stack(padded).to(surfaces[0].device)
        out._grid = torch.cat([s._grid for s in surfaces]).to(surfaces[0].device)
        if all(s.num_patients == 1 and s.device == out.device for s in surfaces):
            # the stacked table is the one copy: each surface reads its own rows of it (the
            # same values, padding beyond its grid never read), so an env over P patients
            # holds their skins once, not twice
            for i, s in enumerate(surfaces):
                s._table = out._table[i : i + 1]
        return out

    @property
    def num_patients(self) -> int:
        return self._table.shape[0]

    # ------------------------------------------------------------------ build
    @classmethod
    def from_patient(cls, patient: Volume, normal_sigma: float = 0.008) -> SkinSurface:
        """Skin height from the first body voxel of each (x, z) column, refined to the sub-voxel
        crossing of the CT through -500 HU (partial-volume accurate)."""
        labels = patient.labels.numpy()
        ct = patient.ct.numpy()
        body = labels > 0
        has = body.any(axis=1)
        if not has.any():
            raise ValueError(f"{patient.name}: label map has no body voxels; cannot find the skin")
        first = body.argmax(axis=1)  # (X, Z)
        ny = ct.shape[1]
        # CT values at rows first-2 .. first+2 of every column.
        offs = np.arange(-2, 3)
        rows = np.clip(first[..., None] + offs, 0, ny - 1)  # (X, Z, 5)
        vals = np.take_along_axis(ct.transpose(0, 2, 1), rows, axis=2)
        below = vals[..., :-1] < SKIN_HU_THRESHOLD
        above = vals[..., 1:] >= SKIN_HU_THRESHOLD
        cross = below & above
        k = np.where(cross.any(-1), cross.argmax(-1), 2)  # fallback: the first body row
        v0 = np.take_along_axis(vals, k[..., None], 2)[..., 0]
        v1 = np.take_along_axis(vals, k[..., None] + 1, 2)[..., 0]
        frac = np.where(
            cross.any(-1), np.clip((SKIN_HU_THRESHOLD - v0) / np.maximum(v1 - v0, 1e-6), 0, 1), 0.5
        )
        row = first + offs[k] + frac  # fractional row of the crossing
        row = np.where(cross.any(-1), row, first - 0.5)
        if not has.all():  # columns beside the body: nearest column's height
            idx = ndimage.distance_transform_edt(~has, return_distances=False, return_indices=True)
            row = row[idx[0], idx[1]]
        sp, org = patient.spacing, patient.origin
        height = org[1] + row * sp[1]
        return cls(height, org[0], org[2], sp[0], sp[2], normal_sigma)

    def to(self, device: torch.device | str) -> SkinSurface:
        """Move the lookup table to a device (in place); returns self."""
        self._table = self._table.to(device)
        self._grid = self._grid.to(device)
        return self

    @property
    def device(self) -> torch.device:
        return self._table.device

    # ---------------------------------------------------------------- queries
    def x_range(self, patient: int = 0) -> tuple[float, float]:
        """(min, max) x of a patient's skin grid, metres."""
        x0, _, dx, _, nx, _ = self._grid[patient].tolist()
        return x0, x0 + dx * (nx - 1)

    def z_range(self, patient: int = 0) -> tuple[float, float]:
        """(min, max) z of a patient's skin grid, metres."""
        _, z0, _, dz, _, nz = self._grid[patient].tolist()
        return z0, z0 + dz * (nz - 1)

    def _lookup(
        self, x: torch.Tensor, z: torch.Tensor, patient: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Bilinear (..., 4) [height, nx, ny, nz]; queries outside the grid clamp to its edge."""
        t = self._table
        if patient is None:
            p = torch.zeros(x.shape, dtype=torch.long, device=t.device)
        else:
            p = torch.as_tensor(patient, dtype=torch.long, device=t.device).expand(x.shape)
        g = self._grid[p].to(x.dtype)  # (..., 6)
        nx, nz = g[..., 4], g[..., 5]
        fx = torch.minimum(((x - g[..., 0]) / g[..., 2]).clamp_min(0), nx - 1)
        fz = torch.minimum(((z - g[..., 1]) / g[..., 3]).clamp_min(0), nz - 1)
        i0 = torch.minimum(fx.floor(), nx - 2).long()
        k0 = torch.minimum(fz.floor(), nz - 2).long()
        wx = (fx - i0).unsqueeze(-1).to(t.dtype)
        wz = (fz - k0).unsqueeze(-1).to(t.dtype)
        v00, v10 = t[p, i0, k0], t[p, i0 + 1, k0]
        v01, v11 = t[p, i0, k0 + 1], t[p, i0 + 1, k0 + 1]
        return (v00 * (1 - wx) + v10 * wx) * (1 - wz) + (v01 * (1 - wx) + v11 * wx) * wz

    def height(
        self, x: torch.Tensor, z: torch.Tensor, patient: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Skin y (metres) at (x, z), any matching shapes; ``patient`` indexes stacked skins."""
        return self._lookup(x, z, patient)[..., 0]

    def normal(
        self, x: torch.Tensor, z: torch.Tensor, patient: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(..., 3) unit inward normals (into the body, +y mostly) at (x, z)."""
        return normalize(self._lookup(x, z, patient)[..., 1:])

    def point(
        self, x: torch.Tensor, z: torch.Tensor, patient: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(..., 3) skin points at (x, z)."""
        return torch.stack([x, self.height(x, z, patient), z], -1)

    def aim(
        self,
        target: torch.Tensor,
        patient: torch.Tensor | None = None,
        iterations: int = 12,
        step: float = 5e-4,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(x, z) of the skin point whose beam, the inward normal, passes through ``target``
        (..., 3) m in {P}: the probe position that images the target on the beam's axis at any
        yaw. Newton's method on the beam's miss of the target in x and z (the 2 x 2 Jacobian by
        central differences of ``step`` m), started straight above the target; float64.

        The miss left (the target's distance from the beam) is ``beam_miss``; a target the skin
        has no such point for (it lies outside the grid's reach) ends at the grid's edge."""
        target = target.to(torch.float64)
        x, z = target[..., 0].clone(), target[..., 2].clone()

        def miss(dx: float, dz: float) -> torch.Tensor:
            return self._miss(x + dx, z + dz, target, patient)

        for _ in range(iterations):
            r = miss(0.0, 0.0)
            jx = (miss(step, 0.0) - miss(-step, 0.0)) / (2 * step)
            jz = (miss(0.0, step) - miss(0.0, -step)) / (2 * step)
            jac = torch.stack([jx, jz], -1)  # (..., 2 residuals, 2 unknowns)
            d = torch.linalg.solve(jac, r.unsqueeze(-1)).squeeze(-1)
            x, z = x - d[..., 0], z - d[..., 1]
        return x, z

    def beam_miss(
        self,
        x: torch.Tensor,
        z: torch.Tensor,
        target: torch.Tensor,
        patient: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(...) m: the distance of ``target`` (..., 3) from the beam (the inward normal's
        line) at skin point (x, z)."""
        s = self.point(x, z, patient).to(torch.float64)
        n = self.normal(x, z, patient).to(torch.float64)
        d = target.to(torch.float64) - s
        return (d - (d * n).sum(-1, keepdim=True) * n).norm(dim=-1)

    def _miss(self, x, z, target, patient) -> torch.Tensor:
        """(..., 2): the x and z components of the target's offset from its nearest point on
        the beam at (x, z) (zero where the beam passes through it)."""
        s = self.point(x, z, patient).to(torch.float64)
        n = self.normal(x, z, patient).to(torch.float64)
        d = s - target
        r = d - (d * n).sum(-1, keepdim=True) * n
        return r[..., [0, 2]]

    def surface_pose(
        self,
        x: torch.Tensor,
        z: torch.Tensor,
        yaw: torch.Tensor,
        tilt: torch.Tensor | None = None,
        patient: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Surface command -> probe pose in {P}.

        Returns (pos (..., 3), rot (..., 3, 3)); rot's columns are x_U, y_U, z_U, z_U along the
        (tilted) inward normal, pos = probe-face centre on the skin.
        """
        look = self._lookup(x, z, patient)
        z0 = normalize(look[..., 1:])
        c, s = torch.cos(yaw).to(z0), torch.sin(yaw).to(z0)
        # Lift (cos yaw, ., sin yaw) onto the tangent plane along y (n_y > 0 on the back).
        t = -(c * z0[..., 0] + s * z0[..., 2]) / z0[..., 1]
        xu = normalize(torch.stack([c, t, s], -1))
        y0 = torch.linalg.cross(z0, xu)
        if tilt is None:
            yu, zu = y0, z0
        else:
            ct, st = torch.cos(tilt).unsqueeze(-1).to(z0), torch.sin(tilt).unsqueeze(-1).to(z0)
            yu, zu = y0 * ct + z0 * st, z0 * ct - y0 * st
        pos = torch.stack([x.to(z0), look[..., 0], z.to(z0)], -1)
        return pos, torch.stack([xu, yu, zu], -1)

    def command_from_pose(
        self, pos: torch.Tensor, rot: torch.Tensor, patient: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Measured surface command (x, z, yaw, tilt) of a probe pose; inverse of surface_pose
        for poses on the surface. yaw in [0, 2*pi)."""
        x, z = pos[..., 0], pos[..., 2]
        xu, zu = rot[..., :, 0], rot[..., :, 2]
        yaw = torch.remainder(torch.atan2(xu[..., 2], xu[..., 0]), 2 * torch.pi)
        n = self.normal(x, z, patient)
        y0 = normalize(torch.linalg.cross(n, xu))
        tilt = torch.atan2(-(zu * y0).sum(-1), (zu * n).sum(-1))
        return x, z, yaw, tilt
