"""Soft tissue that gives under the probe: quasi-static compression by the probe's contact force.

A sonographer presses the probe: fat and muscle under it compress, bone comes closer. The model,
per env and per image column (beam), batched:

1. **Pressure.** The contact force F (N) spreads uniformly over the probe's footprint
   (``probe_footprint``: the array's width x an elevation width): p = F / A (a flexible
   footprint).
2. **Stress under the footprint.** The vertical stress at a point (x, y) across the face and z
   below it is p I(x, y, z), I the influence factor of a uniformly loaded rectangle on an
   elastic half-space (Boussinesq's solution integrated over a rectangle; Newmark 1935, Univ.
   Illinois Eng. Exp. Station Circular 24). I = 1 at the face under the footprint; it falls
   with depth as the load spreads (under the centre of a 75 x 10 mm footprint: 0.55 at 10 mm,
   0.30 at 20 mm, 0.08 at 60 mm) and beyond the footprint's edges over a distance of the order
   of the depth (1/2 at an edge just under the face). This is how the displacement decays
   beyond the footprint: the volume probe's outer elevation slices, at its face's edges, and
   any column outside the array are pressed less.
3. **Strain of each sample along the beam** (uniaxial, 1-D): eps = eps_max (1 - exp(-sigma /
   (E eps_max))), E the tissue's small-strain Young's modulus (``YOUNG_MODULUS``). At small
   stress eps = sigma / E (linear elasticity); the tangent modulus E / (1 - eps / eps_max)
   grows as the tissue compresses, as tissue stiffens under an ultrasound probe in vivo
   (Isogai et al. 2022: subcutaneous tissue 26 kPa at 1 N, 2.2 MPa at 30 N; muscle 62 kPa at
   5 N, 0.44 MPa at 30 N), and no sample compresses by more than ``MAX_STRAIN`` = 0.5, so
   tissue never inverts. Bone, air, gel, fluid and lung do not compress.
4. **Bone is rigid and fixed.** The first bone sample of a beam rests on deeper structures taken
   as fixed: the tissue between the face and it is squeezed against it. A beam without bone is
   squeezed against its deepest sample (the image's bottom), taken as fixed. In the probe's
   frame (the image's: row 0 at the face, which moves with the skin) a point at undeformed
   depth s moves up by c(s), the compression of everything between the face and it; bone and
   everything behind it move up by the beam's total compression U: the probe sank by U.
5. **The warp.** The deformed image's row at depth d shows the undeformed point s with
   s - c(s) = d (c' = eps <= 0.5, so the map is monotone): the slicer samples CT and labels at
   s, so the ultrasound image and the label image move together
   (``sonogym.ultrasound.slicer.Slicer``, ``warp=``).

Limits: quasi-static (no viscoelastic creep or rate dependence), no friction or lateral sliding
(points move along the beam only), no bulging of tissue beside the footprint, the flexible
footprint's uniform pressure rather than a rigid face's (a rigid face would load thin, stiff
columns such as the one over a spinous process more), depth measured from the face, one
modulus per tissue class (no anisotropy, no muscle tone), and speckle drawn at the image's
pixels, so it does not follow the tissue as the force changes (the anatomy does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from sonogym.ultrasound._workspace import Workspace, exp2_
from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.ultrasound.tissues import PHYSICAL_DEFAULT_TISSUE, PHYSICAL_LABEL_TISSUE

#: Counts changes to the model (parameters, equations) that change images; results record it
#: (``sonogym.envs.identity``).
COMPRESSION_VERSION = 1

#: N: the largest contact force the envs take (``contact_force``, the force action's range):
#: the largest load Isogai et al. (2022) applied in vivo with an ultrasound probe. Clinical
#: scanning typically stays well below it (our reading; we cite no survey of probe forces).
MAX_CONTACT_FORCE = 30.0

#: Largest compressive strain of any sample (tissue cannot invert): the strain saturates here.
MAX_STRAIN = 0.5

#: m: elevation width of a 2-D linear probe's face (our choice: linear arrays' lenses are 5-15
#: mm across). A volume probe's face spans its elevation slices.
ELEVATION_WIDTH_2D = 0.01

#: Young's modulus (Pa) per tissue class of the ``physical`` tissue table
#: (``sonogym.ultrasound.tissues.PHYSICAL_LABEL_TISSUE``); ``math.inf``: does not compress.
#: Sources:
#: - skin: 0.42-0.85 MPa in vivo (Agache et al. 1980, Arch Dermatol Res 269:221-232); 0.42 MPa.
#: - fat: subcutaneous fat compressed in vivo under an ultrasound probe, 26.1 +- 19.0 kPa at
#:   1 N (Isogai et al. 2022, J Phys Ther Sci 34:777-783); fat in compression at 5-20 %
#:   precompression 18-24 kPa (Krouskop et al. 1998, Ultrasonic Imaging 20:260-274); 26 kPa.
#: - muscle: 62.2 +- 10.3 kPa at 5 N, in vivo under the probe (Isogai et al. 2022); 62 kPa.
#: - ligament (spinal ligaments) and fascia (thoracolumbar fascia; both label 123, 124):
#:   collagenous layers with tensile moduli of order 10 MPa (lumbar ligaments, Pintar et al.
#:   1992, J Biomech 25:1351-1356) and above (thoracolumbar fascia, tensile tests: Creze et al.
#:   2025, J Mech Behav Biomed Mater); no compressive modulus through their thickness is
#:   published that we know of: 1 MPa (ours), so that these 1-3 mm layers compress by < 0.1 mm.
#: - soft tissue, organs, blood, nerve, brain: 40 kPa (ours, between fat and muscle).
#: - cartilage (intervertebral discs, costal cartilage): 5 MPa (ours; they lie behind bone
#:   or beside it and barely load).
#: - bone, air, gel, fluid (confined CSF, urine, bile), lung: do not compress.
YOUNG_MODULUS: dict[str, float] = {
    "air": math.inf,
    "gel": math.inf,
    "skin": 420e3,
    "fat": 26e3,
    "muscle": 62e3,
    "soft_tissue": 40e3,
    "liver": 40e3,
    "kidney": 40e3,
    "blood": 40e3,
    "fluid": math.inf,
    "lung": math.inf,
    "bone": math.inf,
    "ligament": 1e6,
    "cartilage": 5e6,
    "nerve": 40e3,
    "brain": 40e3,
}

#: m: the compression is computed on beams about this far apart across the image
#: (``TissueCompression``'s default ``stride``; along each beam at every slicer sample, where
#: layers and the bone surface need them) and interpolated to the image's columns: the
#: layers vary slowly across the beams, and the cost falls with the spacing.
WARP_GRID = 2e-3

#: Tissue classes a beam rests on: the first such sample and everything behind it stay fixed.
SUPPORT_TISSUES = frozenset({"bone"})


@dataclass(frozen=True)
class CompressionParams:
    """The tissue model's parameters (module docstring).

    Attributes:
        young_modulus: Pa per tissue class of the ``physical`` table; inf: rigid.
        max_strain: largest compressive strain (0 < max_strain < 1).
        support: tissue classes that hold a beam fixed.
    """

    young_modulus: dict[str, float] = field(default_factory=lambda: dict(YOUNG_MODULUS))
    max_strain: float = MAX_STRAIN
    support: frozenset[str] = SUPPORT_TISSUES

    def __post_init__(self) -> None:
        if not 0.0 < self.max_strain < 1.0:
            raise ValueError(f"max_strain must be in (0, 1), got {self.max_strain}")
        bad = {k: v for k, v in self.young_modulus.items() if not v > 0}
        if bad:
            raise ValueError(f"Young's moduli must be > 0 Pa (inf: rigid), got {bad}")

    def compliance_by_label(self) -> torch.Tensor:
        """(256,) float32, 1 / E (per Pa) of every label id's tissue; 0 where it is rigid."""
        values = []
        for label in range(256):
            tissue = PHYSICAL_LABEL_TISSUE.get(label, PHYSICAL_DEFAULT_TISSUE)
            values.append(1.0 / self.young_modulus[tissue])
        return torch.tensor(values, dtype=torch.float32)

    def support_by_label(self) -> torch.Tensor:
        """(256,) uint8, 1 for label ids whose tissue holds a beam fixed (bone)."""
        tissue = [PHYSICAL_LABEL_TISSUE.get(i, PHYSICAL_DEFAULT_TISSUE) for i in range(256)]
        return torch.tensor([t in self.support for t in tissue], dtype=torch.uint8)

    @property
    def softest(self) -> float:
        """Pa, the smallest Young's modulus of a compressible tissue."""
        return min(v for v in self.young_modulus.values() if math.isfinite(v))


# --------------------------------------------------------------------------- pure functions


def probe_footprint(probe: ProbeGeometry) -> tuple[float, float]:
    """(lateral, elevation) size of the probe's face on the skin, m: the array's width; the
    elevation width ``ELEVATION_WIDTH_2D`` for a 2-D probe, the span of the elevation slices
    for a volume probe (its face covers them)."""
    elevation = (probe.elevation_px - 1) * probe.elevation_spacing
    return probe.width, max(ELEVATION_WIDTH_2D, elevation)


def contact_pressure(force: torch.Tensor, footprint: tuple[float, float]) -> torch.Tensor:
    """Pa: force (N) spread over the footprint (lateral, elevation; m)."""
    return force / (footprint[0] * footprint[1])


def corner_influence(b: torch.Tensor, l_: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Vertical stress / p at depth z below a corner of a uniformly loaded b x l rectangle on
    an elastic half-space (Newmark 1935). Odd in b and in l, so rectangles of signed sides
    superpose (``rectangle_influence``). Tensors broadcast; float64 recommended."""
    m, n = b / z, l_ / z
    m2, n2 = m * m, n * n
    s = torch.sqrt(m2 + n2 + 1)
    first = 2 * m * n * s * (m2 + n2 + 2) / ((m2 + n2 + 1 + m2 * n2) * (m2 + n2 + 1))
    return (first + torch.atan2(2 * m * n * s, m2 + n2 + 1 - m2 * n2)) / (4 * math.pi)


def rectangle_influence(
    x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, half_x: float, half_y: float
) -> torch.Tensor:
    """I(x, y, z): vertical stress / p at (x, y) across and z below the face (m) of a uniform
    pressure p on the rectangle |x| <= half_x, |y| <= half_y: the four corner rectangles of
    signed sides meeting at the point (exact inside and outside the footprint)."""
    z = z.clamp_min(1e-9)
    return (
        corner_influence(half_x - x, half_y - y, z)
        + corner_influence(half_x + x, half_y - y, z)
        + corner_influence(half_x - x, half_y + y, z)
        + corner_influence(half_x + x, half_y + y, z)
    )


def strain(stress: torch.Tensor, compliance: torch.Tensor, max_strain: float) -> torch.Tensor:
    """Compressive strain of samples under ``stress`` (Pa) with ``compliance`` 1 / E (per Pa;
    0: rigid): eps_max (1 - exp(-stress compliance / eps_max)) (module docstring, step 3)."""
    return max_strain * -torch.expm1(-stress * compliance / max_strain)


def warp_shift(
    eps: torch.Tensor, free: torch.Tensor, ws: Workspace | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """How far below each row the compressed image samples.

    Args:
        eps: (..., H) float32 strain of each sample along the beam; sample k stands for the
            cell of one row around it, rows k - 1/2 to k + 1/2 (row 0 at the face).
        free: (..., H) float32, 1 where the sample may compress, 0 where it holds the beam
            fixed (bone): that sample and the ones behind it do not compress.
        ws: scratch buffers (None: fresh tensors).

    Returns:
        (shift, total): shift (..., H) float32 in rows: the deformed image's row j shows the
        undeformed point at row j + shift[j], the solution of s - c(s) = j on the piecewise
        linear compression c(s) of everything between the face and s (exact); total (...,),
        the beam's compression U in rows (at its support, or at its last sample).

    A cell of strain eps shrinks to 1 - eps >= 1 - ``MAX_STRAIN`` = 0.5 rows, so it holds at
    most one whole row of the deformed image: each cell writes the shift of the row it holds,
    a scatter without collisions (no search). Float masks throughout: they are the fast ones.
    """
    ws = ws or Workspace(eps.device)
    shape, h = eps.shape, eps.shape[-1]
    e = ws.get("ws_e", shape, eps.dtype)
    torch.cumprod(free, -1, out=e)  # 1 before the first support sample, then 0
    e.mul_(eps)
    below = ws.get("ws_below", shape, eps.dtype)  # c at each cell's deep end
    torch.cumsum(e, -1, out=below)
    total = below[..., -1].clone()
    above = below.sub_(e)  # c at each cell's shallow end (in place: below is not used again)
    # the shallow end of cell k, at row k - 1/2 before, ends up at row k - 1/2 - c
    top = ws.get("ws_top", shape, eps.dtype)
    rows = torch.arange(h, dtype=eps.dtype, device=eps.device) - 0.5
    torch.sub(rows, above, out=top)
    row = ws.get("ws_row", shape, eps.dtype)
    torch.ceil(top, out=row)  # the first whole row at or below it
    # ... held by the cell when it lies above the cell's deep end, top + 1 - e
    slack = ws.get("ws_slack", shape, eps.dtype)
    torch.sub(row, top, out=slack)  # row - top, in [0, 1)
    # 1 where the cell holds no row (slack + e < 1.5: floor is 0 or 1; float masks are fast)
    outside = torch.add(slack, e, out=top).floor_()  # (top is not used again)
    # ... then it writes past the rows: row + outside (h - row)
    row.addcmul_(outside, row.neg().add_(h))
    index = ws.get("ws_index", shape, torch.int64)
    index.copy_(row)
    # s = k - 1/2 + (j - top) / (1 - e), so s - j = c + (j - top) e / (1 - e)
    gain = e.div_(torch.sub(1, e, out=top))  # e / (1 - e), in place of e
    shift_k = slack.mul_(gain).add_(above)
    out = ws.get("ws_out", (*shape[:-1], h + 1), eps.dtype)
    out.copy_(total[..., None].expand(out.shape))  # rows below every cell: all of U
    out.scatter_(-1, index, shift_k)
    return out[..., :h], total


# ------------------------------------------------------------------------- the batched model


class TissueCompression:
    """The compression model for one slicer's sampling grid (``Slicer.block`` pixels per
    sample), computed on a grid ``stride`` times coarser, for envs of one footprint.

    Args:
        probe: the sampled pixel grid.
        block: (kz, kx) pixels per slicer sample (``Slicer.block``).
        footprint: (lateral, elevation) size of the face, m (default ``probe_footprint(probe)``;
            give the imaging probe's when ``probe`` is a single beam of it).
        params: the tissue model.
        device: where the tables live.
        stride: (sd, sl) slicer samples per model sample along and across the beam (default:
            (1, beams about ``WARP_GRID`` apart)); (1, 1) computes it at every sample.
    """

    def __init__(
        self,
        probe: ProbeGeometry,
        block: tuple[int, int] = (1, 1),
        footprint: tuple[float, float] | None = None,
        params: CompressionParams | None = None,
        device: torch.device | str = "cpu",
        stride: tuple[int, int] | None = None,
    ) -> None:
        self.probe, self.block = probe, tuple(block)
        self.footprint = footprint or probe_footprint(probe)
        self.params = params or CompressionParams()
        self.device = torch.device(device)
        if stride is None:
            stride = (1, max(1, round(WARP_GRID / (block[1] * probe.width_spacing))))
        #: (sd, sl): slicer samples per model sample (``DepthWarp.stride``)
        self.stride = tuple(int(v) for v in stride)
        kz, kx = self.block[0] * self.stride[0], self.block[1] * self.stride[1]
        hc, wc = -(-probe.depth_px // kz), -(-probe.width_px // kx)
        #: m per model sample along the beam
        self.row = kz * probe.depth_spacing
        # sample centres: block centres in {U} (the slicer's sampling points)
        x = torch.arange(wc, dtype=torch.float64) * kx + (kx - 1) / 2 - (probe.width_px - 1) / 2
        x = x * probe.width_spacing
        y = probe.elevation_positions(dtype=torch.float64)
        z = (torch.arange(hc, dtype=torch.float64) * kz + (kz - 1) / 2) * probe.depth_spacing
        half_x, half_y = self.footprint[0] / 2, self.footprint[1] / 2
        infl = rectangle_influence(x[None, :, None], y[:, None, None], z[None, None, :], half_x,
                                   half_y)  # fmt: skip
        #: (E, Wc, Hc) float32: stress / pressure at each sample
        self.influence = infl.float().contiguous().to(self.device)
        self.compliance = self.params.compliance_by_label().to(self.device)
        #: (256,) float32: 1 for a label whose tissue may compress, 0 for one that holds the
        #: beam (bone)
        self.free = (1 - self.params.support_by_label().float()).to(self.device)
        self.centre = ((probe.elevation_px - 1) / 2, (wc - 1) / 2)
        self._max_rows: int | None = None

    def max_shift(self, force: float = MAX_CONTACT_FORCE) -> float:
        """m: a bound on any sample's shift under ``force`` (N): the softest tissue everywhere,
        under the footprint's centre, where the stress is the largest at every depth; how much
        deeper than the image a warped slicer may sample."""
        pr = self.probe
        z = (torch.arange(pr.depth_px, dtype=torch.float64) + 0.5) * pr.depth_spacing
        zero = torch.zeros((), dtype=torch.float64)
        infl = rectangle_influence(zero, zero, z, self.footprint[0] / 2, self.footprint[1] / 2)
        p = contact_pressure(torch.tensor(float(force), dtype=torch.float64), self.footprint)
        eps = strain(p * infl, torch.tensor(1 / self.params.softest), self.params.max_strain)
        return float(eps.sum()) * pr.depth_spacing + self.row

    def max_rows(self, force: float = MAX_CONTACT_FORCE) -> int:
        """``max_shift`` in samples (kept for ``MAX_CONTACT_FORCE``)."""
        if force == MAX_CONTACT_FORCE:
            if self._max_rows is None:
                self._max_rows = math.ceil(self.max_shift(force) / self.row)
            return self._max_rows
        return math.ceil(self.max_shift(force) / self.row)

    def bind(self, force: torch.Tensor, max_force: float | None = None) -> CompressionWarp:
        """The warp of N envs pressed with ``force`` (N,) newtons (at most ``max_force``; None:
        read it), for one slicer call."""
        return CompressionWarp(self, force, max_force)


class CompressionWarp:
    """One slicer call's warp (``Slicer.__call__(warp=)``): called per chunk of envs with their
    undeformed label samples, returns the rows to sample below each sample; keeps each env's
    compression under the image's centre (``centre``, m).

    ``max_force`` (N) bounds ``force``: it sets how deep the slicer may sample (its crop
    check); None reads the largest force (a wait on a GPU)."""

    def __init__(
        self, model: TissueCompression, force: torch.Tensor, max_force: float | None = None
    ) -> None:
        self.model = model
        force = torch.as_tensor(force, dtype=torch.float32, device=model.device).reshape(-1)
        self.pressure = contact_pressure(force, model.footprint)
        #: (N,) float32, m: the beam under the image's centre compressed by this much
        self.centre = torch.zeros_like(force)
        if max_force is None:
            max_force = float(force.max()) if force.numel() else 0.0
        #: rows (of the model's samples) any shift stays within (the slicer's crop check)
        self.max_rows = model.max_rows(max_force)
        self.stride = model.stride

    def __call__(self, labels: torch.Tensor, envs: slice, ws: Workspace) -> torch.Tensor | None:
        """labels (n, E, Wc, Hc) uint8 of envs ``envs`` (depth last) -> shift (n, E, Wc, Hc)
        float32 in sample rows."""
        m, shape = self.model, labels.shape
        lab = ws.get("warp_lab", shape, torch.int32)
        lab.copy_(labels)
        eps = ws.get("warp_eps", shape, torch.float32)
        torch.index_select(m.compliance, 0, lab.view(-1), out=eps.view(-1))
        # the exponent -sigma / (E eps_max) in base 2 (exp2_: the same bits in any batch)
        scale = self.pressure[envs] * (-1.0 / (m.params.max_strain * math.log(2)))
        eps.mul_(m.influence).mul_(scale.view(-1, 1, 1, 1))
        exp2_(eps)
        eps.neg_().add_(1).mul_(m.params.max_strain)  # eps_max (1 - exp(-sigma / (E eps_max)))
        free = ws.get("warp_free", shape, torch.float32)
        torch.index_select(m.free, 0, lab.view(-1), out=free.view(-1))
        shift, total = warp_shift(eps, free, ws)
        self.centre[envs] = _centre_value(total, m.centre) * m.row
        return shift.clamp_(max=self.max_rows)


def _centre_value(total: torch.Tensor, centre: tuple[float, float]) -> torch.Tensor:
    """(n,) the mean of ``total`` (n, E, W) over the one, two or four entries at the centre."""
    e, w = centre
    es = sorted({math.floor(e), math.ceil(e)})
    cs = sorted({math.floor(w), math.ceil(w)})
    return total[:, es][:, :, cs].flatten(1).mean(1)
