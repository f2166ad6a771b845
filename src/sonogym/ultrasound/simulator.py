"""Model-based ultrasound simulation from CT and label slices (the paper's appendix model).

``ModelBasedSimulator(model).simulate(slices)`` turns the slicer's CT + label samples into
B-mode images in [0, 1], batched over envs and elevation slices, with the same code on CPU and
CUDA. Every image is a function of its slices and its patient-fixed speckle only: the same pose
gives the same image, and the result does not depend on the batch it was computed in.

Two ultrasound models (docs/design.md):

``reference`` -- the reference implementation's CT-mode model, exactly
(the authors' reference code), with its constants restated in physical units so that
at 0.5 mm pixels they equal the reference's per-pixel constants:

1. C = (clip(HU, -300, 3000) + 300) / 3300 * 255, Z = 100 C;
2. rho(y) = ((Z(y-1) - Z(y)) / (Z(y-1) + Z(y) + 1e-5))^2, reflect padding at the top row;
3. A_B(y) = exp(-0.02/mm * dz * sum_{y' <= y}(alpha(y') - 0.2)), A_R likewise with beta = 0;
4. R = min(A_R rho, 0.1) (*) PSF_R, PSF_R = exp(-d^2 / 2 (1.5 mm)^2) both ways (the reference's
   unnormalised 11 x 11 kernel of sigma 3 px);
5. S = (mu0 + sigma0 N0) [N1 <= mu1] (1 + 0.08 V), V ~ N(0, 1) on 15 mm patient-space cells,
   per env (the reference shared env 0's field between all envs: a bug we do not copy);
6. B = A_B (S (*) PSF_B), PSF_B of sigma (0.5 mm axial, 1 mm lateral);
7. raw = 20 R + B; observation = clip(0.02 raw, 0, 1).

Kernels are rescaled to the reference kernels' sums (lateral sum for PSF_R, both sums for PSF_B),
so a coarser probe sees an interface or a speckle region as bright as the 0.5 mm probe does
(the reference instead scaled sigma by 1/sqrt(s) and kept the per-pixel attenuation: a quirk).
Deviations: air below the gel band blocks the beam (the reference zeroed a whole image when the
probe lost contact); CT jumps inside the gel band do not reflect (the reference imaged from 3 mm
below the skin, so its images had no skin line); large-scale cells are fixed in patient space.

``physical`` -- the paper's full model with physical units:

1. impedance Z from the label's tissue, refined by the CT: Z = Z_tissue * m(HU) / m(HU_tissue),
   m a monotone CT -> impedance curve through the literature values (tissues.HU_IMPEDANCE), so
   the partial-volume ramp of an interface carries the impedance across smoothly;
2. near label boundaries (indicator G, widened by 1 mm to cover the CT's partial-volume ramp,
   so curved interfaces give continuous lines instead of the label map's voxel staircase),
   amplitude reflection R = (Z(y) - Z(y-1)) / (Z(y) + Z(y-1)) between neighbouring pixels,
   summed over 1 mm of depth (the ramp of one CT voxel) to recover a sharp interface's |R|,
   times cos(theta)^n, theta the angle between the beam and the boundary normal, taken from the
   CT gradient (smooth where the label map is a voxel staircase);
3. round-trip amplitude E(y) = exp(-sum_{y' < y} [2 alpha f dz / 8.686 - ln(1 - R^2)]): attenuation
   in dB/cm/MHz at the centre frequency and transmission loss through every interface above;
   air behind skin transmits ~1e-3 each way, so no signal passes an air gap;
4. complex scatterers s = T (1 + 0.08 V) (g_re + i g_im), T = (mu0 + sigma0 N0)[N1 <= mu1] as in
   the paper, g ~ N(0, 1) from the same patient-fixed hash, scaled so that dense unit-amplitude
   tissue sits ``backscatter_level`` dB below a perfect flat reflector;
5. field = E (R cos(theta)^n + s), convolved with a Gaussian PSF whose axial width is half the
   pulse length (``pulse_cycles`` wavelengths) and lateral width lambda * F-number;
6. envelope |field| (Rayleigh in homogeneous tissue), time-gain compensation of
   ``tgc_alpha`` dB/cm/MHz round trip, log compression to ``dynamic_range`` dB, in [0, 1].

Gel band: air in the first ``gel_depth`` of every column is coupling gel (the probe's face is on
the skin, whose voxel may read air; real probes press a few mm into the skin).

Performance: each step is one or a few full-array passes; table lookups are single gathers
``torch.take(table, labels)``; the speckle is a hash (speckle.py); PSFs are shifted multiply-adds
(psf.py); on CPU the batch is processed in chunks of ``chunk_pixels`` so the temporaries stay in
cache, and with more than one torch thread the chunks run on that many threads at once
(``ChunkRunner``; same images).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import torch

from sonogym.ultrasound import psf as _psf
from sonogym.ultrasound._workspace import ChunkRunner, Workspace, exp2_
from sonogym.ultrasound.aliases import canonical_name
from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.ultrasound.slicer import Slices
from sonogym.ultrasound.speckle import gaussian_quantiles, lattice_bits, seed_mix
from sonogym.ultrasound.tissues import (
    GEL,
    TissueTable,
    impedance_of_hu,
    physical_table,
    reference_table,
)

#: Bits of the per-pixel scatterer lookup: 8 for the density threshold, 4 for the amplitude.
_DENSITY_BITS = 8
_AMPLITUDE_BITS = 4
_LUT_BITS = _DENSITY_BITS + _AMPLITUDE_BITS
_LUT_MASK = 2**_LUT_BITS - 1
_GAUSS_BITS = 10
_GAUSS_MASK = 2**_GAUSS_BITS - 1
#: Bits 12-27: a pair of independent N(0, 1) values (8 bits each) for the complex scatterers.
_PAIR_BITS = 16
_PAIR_MASK = 2**_PAIR_BITS - 1
#: CT -> impedance lookup: HU -1024 .. 3071 in 1 HU steps.
_HU_OFFSET = 1024
_HU_LUT = 4096
#: Salt separating the large-scale field's hash from the speckle's.
_LARGE_SCALE_SALT = 0x5A17
#: Attenuation exponent per pixel that stands for "blocked" (exp(-60) ~ 1e-26).
_BLOCK = 60.0
#: Largest attenuation exponent kept: exp(-40) ~ 4e-18 is black, and clamping keeps products
#: clear of float32 denormals (which are ~50x slower on CPU).
_MAX_EXPONENT = 40.0
#: Same for the physical model's amplitudes, which get squared: e^-20 is -174 dB, far below
#: the display's floor, and its square stays a normal float32.
_MAX_LOG_AMPLITUDE = 20.0
_LOG2_E = 1.0 / math.log(2.0)


@dataclass(frozen=True, eq=False)
class ReferenceModel:
    """The ``reference`` model: the reference's CT-mode model (values from
    the authors' reference code, in physical units)."""

    e_s_ratio: float = 20.0  # weight of the reflection term
    i0: float = 1.0  # initial energy
    reflection_clip: float = 0.1  # clip of the per-pixel reflection before the PSF
    attenuation_per_mm: float = 0.02  # f * e per 0.5 mm pixel = 0.01 -> 0.02 per mm per unit alpha
    beta_backscatter: float = 0.2  # TGC_beta, subtracted from alpha for the backscatter
    beta_reflection: float = 0.0  # TGC_edge, same for the reflection
    psf_reflection_sigma: tuple[float, float] = (1.5e-3, 1.5e-3)  # (axial, lateral), m
    psf_backscatter_sigma: tuple[float, float] = (0.5e-3, 1.0e-3)  # (axial, lateral), m
    psf_half_width: float = 2.5e-3  # m (the 11-tap kernel at 0.5 mm)
    psf_reference_spacing: float = 0.5e-3  # m, pixel size the kernel sums are taken at
    ct_range: tuple[float, float] = (-300.0, 3000.0)  # HU mapped linearly to [0, 255]
    impedance_scale: float = 100.0  # Z = impedance_scale * C
    impedance_eps: float = 1e-5  # in the reflection ratio's denominator
    large_scale_amplitude: float = 0.08  # A_l
    large_scale_cell: float = 15e-3  # m (f_l = 30 px at 0.5 mm)
    speckle_cell: float = 0.5e-3  # m, lattice of the scatterer noise
    gel_depth: float = 3e-3  # m, air this close to the face is coupling gel
    gel_hu_threshold: float = -200.0  # HU; in the gel band, CT below it (air) reads as water
    air_blocks: bool = True  # air (label 0) below the gel band stops the beam
    observation_scale: float = 0.02  # raw -> observation, clipped to [0, 1]
    tissues: TissueTable = field(default_factory=reference_table)

    name = "reference"


@dataclass(frozen=True, eq=False)
class PhysicalModel:
    """The ``physical`` model: the paper's full model with literature acoustics.

    The centre frequency is 3.5 MHz, a lumbar curvilinear probe's (2-5 MHz reach the 6-8 cm
    lamina depth): a 10 MHz linear probe would lose 60+ dB in muscle
    before the lamina."""

    frequency: float = 3.5e6  # Hz, centre frequency
    speed_of_sound: float = 1540.0  # m/s
    pulse_cycles: float = 3.0  # pulse length in wavelengths (axial FWHM = half of it)
    f_number: float = 4.0  # lateral FWHM = wavelength * f_number
    psf_truncation: float = 3.0  # PSF half width, in sigmas
    tgc_alpha: float = 0.6  # dB/cm/MHz compensated by TGC (that of generic soft tissue)
    dynamic_range: float = 60.0  # dB mapped to [0, 1]
    gain: float = 0.0  # dB added before log compression
    backscatter_level: float = -30.0  # dB, RMS envelope of dense unit scatterers vs R = 1
    incidence_exponent: float = 1.0  # reflection ~ cos(theta)^n (paper: n = 1)
    incidence_eps: float = 20.0  # HU per pixel: CT gradients below this read as normal incidence
    boundary_halfwidth: float = 1.0e-3  # m; reflections within this of a label boundary (ramp)
    interface_width: float = 1.0e-3  # m; partial reflections summed over this depth (a voxel)
    large_scale_amplitude: float = 0.08
    large_scale_cell: float = 15e-3  # m
    speckle_cell: float = 0.5e-3  # m
    gel_depth: float = 3e-3  # m, air this close to the face is coupling gel
    gel_hu_threshold: float = -200.0  # HU; in the gel band, CT below it (air) reads as gel
    tissues: TissueTable = field(default_factory=physical_table)

    name = "physical"

    @property
    def wavelength(self) -> float:
        """m."""
        return self.speed_of_sound / self.frequency

    @property
    def axial_sigma(self) -> float:
        """PSF sigma along the beam, m (FWHM = half the pulse length)."""
        return self.pulse_cycles * self.wavelength / 2 / 2.3548

    @property
    def lateral_sigma(self) -> float:
        """PSF sigma across the beam, m (FWHM = wavelength * F-number)."""
        return self.wavelength * self.f_number / 2.3548


#: The model-based ultrasound models by name.
US_MODELS: dict[str, type] = {"physical": PhysicalModel, "reference": ReferenceModel}
#: Each model's version: bumped whenever its images for the same slices change, so that results
#: record which images they were measured on (``sonogym.envs.identity``).
MODEL_VERSIONS: dict[str, int] = {"physical": 1, "reference": 1}


def make_model(model: str | ReferenceModel | PhysicalModel) -> ReferenceModel | PhysicalModel:
    """An ultrasound model from its name (or pass a configured model through). ``"sonogym"``,
    the former name of ``"reference"``, is accepted with a ``DeprecationWarning`` until 0.3.0."""
    if isinstance(model, (ReferenceModel, PhysicalModel)):
        return model
    name = canonical_name(model) if isinstance(model, str) else model
    if name not in US_MODELS:
        raise ValueError(f"unknown ultrasound model {model!r}; known models: {sorted(US_MODELS)}")
    return US_MODELS[name]()


def _large_scale_block(h: int, w: int, dz: float, dx: float, limit: float = 2.5e-3) -> int:
    """Largest common divisor k of h and w with k pixels <= ``limit`` metres."""
    g = math.gcd(h, w)
    return max(k for k in range(1, g + 1) if g % k == 0 and (k == 1 or k * max(dz, dx) <= limit))


class _Chunk(NamedTuple):
    """Part of a batch, as a model's chunk step takes it."""

    ct: torch.Tensor  # (B, H, W) float32, HU
    lab: torch.Tensor  # (B, H, W) int32 labels, air in the gel band read as GEL (workspace)
    geom: tuple  # per image: origin, row step, column step (m), speckle and large-scale keys
    k: dict  # the probe's constants (``_constants``)
    display: bool  # map to the display range [0, 1] (else the raw image)
    out: torch.Tensor  # (B, H, W) float32, the images
    ws: Workspace  # the chunk's scratch buffers


def _buf(ws: Workspace, name: str, like: torch.Tensor, dtype=torch.float32) -> torch.Tensor:
    """Scratch buffer ``name`` of ``like``'s shape from the chunk's workspace."""
    return ws.get(name, tuple(like.shape), dtype)


class ModelBasedSimulator:
    """Model-based ultrasound simulator (``UltrasoundSimulator`` protocol).

    Args:
        model: "physical", "reference", or a configured ``PhysicalModel``/``ReferenceModel``.
        device: where the lookup tables live; slices on another device are rejected.
        chunk_pixels: pixels processed per chunk (CPU cache blocking); default 2**19 on CPU,
            everything at once on CUDA.
    """

    def __init__(
        self,
        model: str | ReferenceModel | PhysicalModel = "physical",
        device: torch.device | str = "cpu",
        chunk_pixels: int | None = None,
    ) -> None:
        self.model = make_model(model)
        self.device = torch.device(device)
        if chunk_pixels is None:
            chunk_pixels = 2**19 if self.device.type == "cpu" else 2**40
        self.chunk_pixels = int(chunk_pixels)
        self._consts: dict[ProbeGeometry, dict] = {}
        self._gauss = gaussian_quantiles(_GAUSS_BITS, device=self.device)
        # (g_re, g_im) pairs on a 256 x 256 grid of quantiles: row 0 the real parts, row 1 the
        # imaginary ones, gathered by one index into the planar field
        q = gaussian_quantiles(_PAIR_BITS // 2)
        pairs = torch.stack(torch.meshgrid(q, q, indexing="ij"), 0).reshape(2, -1)
        self._gauss_pairs = pairs.contiguous().to(self.device)
        self._chunks = ChunkRunner(self.device)  # scratch buffers, one set per worker thread

    @property
    def nbytes(self) -> int:
        """Bytes held by lookup tables and scratch buffers."""
        tables = sum(
            v.numel() * v.element_size()
            for k in self._consts.values()
            for v in k.values()
            if isinstance(v, torch.Tensor)
        )
        return tables + self._chunks.nbytes

    # ---------------------------------------------------------------- tables
    def _scatter_lut(self, table: TissueTable, gain: float) -> torch.Tensor:
        """(256 * 2**12,) amplitude T = (mu0 + sigma0 N0) [N1 <= mu1] per (label, 12 random bits).

        Bits 4..11 give U1 (density: N1 <= mu1 <=> U1 <= Phi(mu1)); bits 0..3 give N0."""
        n0 = gaussian_quantiles(_AMPLITUDE_BITS, torch.float64)  # (16,)
        u1 = (torch.arange(2**_DENSITY_BITS, dtype=torch.float64) + 0.5) / 2**_DENSITY_BITS
        mu0, mu1, s0 = (table.column(f) for f in ("mu0", "mu1", "sigma0"))
        dens = 0.5 * (1 + torch.erf(mu1 / math.sqrt(2)))  # Phi(mu1), (256,)
        present = (u1[None, :] <= dens[:, None]).double()  # (256, 256)
        amp = mu0[:, None] + s0[:, None] * n0[None, :]  # (256, 16)
        lut = present[:, :, None] * amp[:, None, :] * gain  # (label, density, amplitude)
        return lut.reshape(-1).float().to(self.device)

    def _constants(self, probe: ProbeGeometry) -> dict:
        if probe in self._consts:
            return self._consts[probe]
        m = self.model
        dz, dx = probe.depth_spacing, probe.width_spacing
        h, w = probe.depth_px, probe.width_px
        dev = self.device
        tab = m.tissues
        y = torch.arange(h, dtype=torch.float64)
        k: dict = {"gel_rows": min(h, int(math.ceil(m.gel_depth / dz - 1e-9)))}
        k["ls_block"] = _large_scale_block(h, w, dz, dx)
        if isinstance(m, ReferenceModel):
            per_px = m.attenuation_per_mm * dz * 1e3
            att = (tab.column("alpha") - m.beta_backscatter) * per_px
            if m.air_blocks:
                att[0] = _BLOCK
            k["att_neg"] = (-att * _LOG2_E).float().to(dev)  # log2 units: one exp2 per pixel
            prof = m.i0 * torch.exp(-per_px * (m.beta_backscatter - m.beta_reflection) * (y + 1))
            k["ar_profile"] = prof.float().to(dev)[:, None]
            lo, hi = m.ct_range
            # rho only depends on ratios of Z = s x, s = impedance_scale * 255 / (hi - lo), with
            # x = clip(HU, lo, hi) - lo: (Zu - Z) / (Zu + Z + eps) = (xu - x) / (xu + x + eps / s).
            k["den_offset"] = m.impedance_eps / (m.impedance_scale * 255.0 / (hi - lo))
            ref = m.psf_reference_spacing
            hw = m.psf_half_width

            def taps(sigma: float, spacing: float, ref_sum: bool) -> list[float]:
                t = _psf.gaussian_taps(sigma, spacing, hw)
                if ref_sum:
                    t = _psf.scaled(t, sum(_psf.gaussian_taps(sigma, ref, hw)))
                return _psf.trimmed(t)

            (sra, srl), (sba, sbl) = m.psf_reflection_sigma, m.psf_backscatter_sigma
            k["psf_r"] = (taps(sra, dz, False), taps(srl, dx, True))
            k["psf_b"] = (taps(sba, dz, True), taps(sbl, dx, True))
            k["lut"] = self._scatter_lut(tab, 1.0)
        else:
            f_mhz = m.frequency * 1e-6
            np_per_db = math.log(10) / 20
            # per-row log-amplitude change: TGC gain minus round-trip attenuation, in log2 units
            # (the amplitude is then one exp2, half the cost of exp on CPU)
            att = 2 * tab.column("alpha") * f_mhz * dz * 1e2 * np_per_db
            tgc = 2 * m.tgc_alpha * f_mhz * dz * 1e2 * np_per_db
            k["gain_rate"] = ((tgc - att) * _LOG2_E).float().to(dev)
            k["inc_block"] = _large_scale_block(h, w, dz, dx, limit=1.0e-3)
            hu = torch.arange(_HU_LUT, dtype=torch.float64) - _HU_OFFSET
            scale = tab.column("impedance") / impedance_of_hu(tab.column("hu"))  # (256,)
            # Z per (label, HU): one gather with index (label << 12) | (HU + 1024)
            k["z_lut"] = (scale[:, None] * impedance_of_hu(hu)[None, :]).reshape(-1).float().to(dev)
            k["z_gel"] = float(tab.params(GEL).impedance)
            k["ramp_rows"] = int(round(m.boundary_halfwidth / dz))
            k["ramp_box"] = 1 + 2 * int(round(m.interface_width / (2 * dz)))
            sa, sl = m.axial_sigma, m.lateral_sigma
            axial = _psf.gaussian_taps(sa, dz, m.psf_truncation * sa)  # peak 1
            lateral = _psf.scaled(_psf.gaussian_taps(sl, dx, m.psf_truncation * sl), 1.0)
            k["psf"] = (axial, lateral)
            energy = sum(t * t for t in axial) * sum(t * t for t in lateral)
            gain = 10 ** (m.backscatter_level / 20) / math.sqrt(2 * energy)
            k["lut"] = self._scatter_lut(tab, gain)
        self._consts[probe] = k
        return k

    # ------------------------------------------------------------------ API
    def simulate(self, slices: Slices, out: torch.Tensor | None = None) -> torch.Tensor:
        """B-mode images (N, E, H, W) float32 in [0, 1] (written into ``out`` if given)."""
        return self._run(slices, True, out)

    def simulate_raw(self, slices: Slices, out: torch.Tensor | None = None) -> torch.Tensor:
        """Images before display mapping: ``reference``: 20 R + B (before x0.02 and clipping);
        ``physical``: the TGC-compensated envelope (before log compression)."""
        return self._run(slices, False, out)

    __call__ = simulate

    def _run(self, slices: Slices, display: bool, out: torch.Tensor | None) -> torch.Tensor:
        if not isinstance(slices, Slices):
            raise TypeError(f"simulate() takes a Slices (from Slicer), got {type(slices).__name__}")
        if slices.ct.device != self.device:
            raise ValueError(
                f"slices are on {slices.ct.device} but the simulator on {self.device}; "
                "build both with the same device"
            )
        if slices.ct.dtype != torch.float32 or slices.labels.dtype != torch.uint8:
            raise TypeError("slices must hold float32 CT and uint8 labels")
        n, e, h, w = slices.ct.shape
        if out is None:
            out = torch.empty(n, e, h, w, dtype=torch.float32, device=self.device)
        elif out.shape != (n, e, h, w) or out.dtype != torch.float32 or not out.is_contiguous():
            raise ValueError(f"out must be a contiguous float32 tensor of shape {(n, e, h, w)}")
        k = self._constants(slices.probe)
        b_all = n * e
        ct = slices.ct.reshape(b_all, h, w)
        lab = slices.labels.reshape(b_all, h, w)
        origin = slices.origin.reshape(b_all, 3)
        row = slices.row_step.repeat_interleave(e, 0)
        col = slices.col_step.repeat_interleave(e, 0)
        seeds = slices.seed.repeat_interleave(e, 0)
        mix = seed_mix(seeds)
        mix_ls = seed_mix(seeds, _LARGE_SCALE_SALT)
        flat = out.view(b_all, h, w)
        step = max(1, self.chunk_pixels // (h * w))
        chunk = (
            self._reference_chunk
            if isinstance(self.model, ReferenceModel)
            else self._physical_chunk
        )

        def run(sl: slice, ws: Workspace) -> None:
            geom = (origin[sl], row[sl], col[sl], mix[sl], mix_ls[sl])
            labels = self._labels(lab[sl], k, ws)
            chunk(_Chunk(ct[sl], labels, geom, k, display, flat[sl], ws))

        self._chunks.run(run, [slice(s, min(b_all, s + step)) for s in range(0, b_all, step)])
        return out

    # -------------------------------------------------------------- shared
    def _labels(self, lab8: torch.Tensor, k: dict, ws: Workspace) -> torch.Tensor:
        """int32 labels (workspace) with air in the gel band replaced by GEL."""
        lab = _buf(ws, "lab", lab8, torch.int32)
        lab.copy_(lab8)
        g = k["gel_rows"]
        if g:
            top = lab[:, :g]
            top.masked_fill_(lab8[:, :g] == 0, GEL)
        return lab

    def _gel_mask(self, ct: torch.Tensor, lab: torch.Tensor, g: int) -> torch.Tensor:
        """(B, g, W) bool: gel, or partial-volume air (CT below the threshold), in the gel band."""
        return (lab[:, :g] == GEL).logical_or_(ct[:, :g] < self.model.gel_hu_threshold)

    def _scatterers(
        self, lab12: torch.Tensor, geom: tuple, k: dict, ws: Workspace
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Scatterer amplitude T (1 + A_l V) per pixel (workspace "amp"), and the pixels' 32
        random bits (workspace "bits"; bits 0-11 are used here). ``lab12``: labels << 12."""
        lab = lab12
        m = self.model
        origin, row, col, mix, mix_ls = geom
        b, h, w = lab.shape
        bits = _buf(ws, "bits", lab, torch.int32)
        key = _buf(ws, "key", lab, torch.int64)
        lattice_bits(origin, row, col, h, w, m.speckle_cell, mix, out=bits, tmp=key)
        idx = key.view(torch.int32).view(-1)[: lab.numel()].view(lab.shape)  # free scratch
        torch.bitwise_and(bits, _LUT_MASK, out=idx)
        idx.bitwise_or_(lab12)
        amp = _buf(ws, "amp", lab, torch.float32)
        torch.index_select(k["lut"], 0, idx.view(-1), out=amp.view(-1))
        if m.large_scale_amplitude:
            kb = k["ls_block"]
            hb, wb = h // kb, w // kb
            o = origin + (kb - 1) / 2 * (row + col)
            v = lattice_bits(o, kb * row, kb * col, hb, wb, m.large_scale_cell, mix_ls)
            v = torch.index_select(self._gauss, 0, v.bitwise_and_(_GAUSS_MASK).view(-1))
            mod = v.view(b, hb, wb).mul_(m.large_scale_amplitude).add_(1.0)
            amp.view(b, hb, kb, w).mul_(mod.repeat_interleave(kb, dim=2).view(b, hb, 1, w))
        return amp, bits

    # ----------------------------------------------------------- reference
    def _reference_chunk(self, chunk: _Chunk) -> None:
        m: ReferenceModel = self.model  # type: ignore[assignment]
        ct, lab, geom, k, display, out, ws = chunk
        g = k["gel_rows"]
        # Attenuation, inclusive of the current pixel: A_B = exp(-sum (alpha - beta_B) dz).
        a_b = _buf(ws, "a", ct)
        torch.index_select(k["att_neg"], 0, lab.view(-1), out=a_b.view(-1))
        exp2_(a_b.cumsum_(1).clamp_(min=-_MAX_EXPONENT * _LOG2_E))
        # Reflection rho = ((Zu - Z) / (Zu + Z + eps))^2 with Z ~ clipped HU (see _constants);
        # reflect padding: the row above row 0 is row 1. Gel reads as water (0 HU).
        x = _buf(ws, "x", ct)
        lo, hi = m.ct_range
        torch.clamp(ct, lo, hi, out=x).sub_(lo)
        if g:
            x[:, :g].masked_fill_(self._gel_mask(ct, lab, g), -lo)
        rho = _buf(ws, "r", ct)
        tmp = _buf(ws, "t", ct)
        if x.shape[1] > 1:
            torch.sub(x[:, :-1], x[:, 1:], out=rho[:, 1:])
            torch.sub(x[:, 1], x[:, 0], out=rho[:, 0])
            torch.add(x[:, :-1], x[:, 1:], out=tmp[:, 1:])
            torch.add(x[:, 1], x[:, 0], out=tmp[:, 0])
        else:
            rho.zero_()
            torch.add(x, x, out=tmp)
        rho.div_(tmp.add_(k["den_offset"])).square_()
        if g:  # no reflections inside the gel band (the reference imaged from 3 mm below skin)
            rho[:, :g] = 0.0
        # R = min(A_R rho, clip) (*) PSF_R, A_R = A_B * exp(-(beta_B - beta_R) dz (y + 1)).
        rho.mul_(a_b).mul_(k["ar_profile"]).clamp_(max=m.reflection_clip)
        refl = _psf.blur_2d(rho, *k["psf_r"], tmp=tmp)
        # B = A_B (S (*) PSF_B).
        amp, _ = self._scatterers(lab.bitwise_left_shift_(_LUT_BITS), geom, k, ws)
        back = _psf.blur_2d(amp, *k["psf_b"], tmp=tmp)
        back.mul_(a_b)
        if m.i0 != 1.0:
            back.mul_(m.i0)
        if display:
            s = m.observation_scale
            torch.add(back.mul_(s), refl, alpha=m.e_s_ratio * s, out=out).clamp_(0.0, 1.0)
        else:
            torch.add(back, refl, alpha=m.e_s_ratio, out=out)

    # ------------------------------------------------------------ physical
    def _physical_chunk(self, chunk: _Chunk) -> None:
        m: PhysicalModel = self.model  # type: ignore[assignment]
        ct, lab, geom, k, display, out, ws = chunk
        g = k["gel_rows"]
        z_gel = k["z_gel"]
        flat_lab = lab.view(-1)
        # Impedance: the tissue's literature value, refined by the CT along the CT -> impedance
        # curve m: Z = Z_tissue * m(HU) / m(HU_tissue). Across an interface's partial-volume
        # ramp the impedance then follows the (smooth, trilinear) CT, not the label staircase.
        hu_idx = _buf(ws, "hu_idx", ct, torch.int32)
        z = _buf(ws, "z", ct)
        tmp = _buf(ws, "t", ct)
        torch.add(ct, _HU_OFFSET + 0.5, out=z).clamp_(0, _HU_LUT - 1)
        hu_idx.copy_(z)  # rounds to the nearest HU
        if g:  # gel and partial-volume air at the skin read as water
            hu_idx[:, :g].masked_fill_(self._gel_mask(ct, lab, g), _HU_OFFSET)
        lab12 = torch.bitwise_left_shift(lab, _LUT_BITS, out=_buf(ws, "lab12", ct, torch.int32))
        torch.index_select(k["z_lut"], 0, hu_idx.bitwise_or_(lab12).view(-1), out=z.view(-1))
        # Amplitude reflection R = (Z(y) - Z(y-1)) / (Z(y) + Z(y-1)) near label boundaries (G,
        # widened to the rows of the CT ramp); gel above row 0.
        refl = _buf(ws, "r", ct)
        torch.sub(z[:, 1:], z[:, :-1], out=refl[:, 1:])
        torch.sub(z[:, 0], z_gel, out=refl[:, 0])
        torch.add(z[:, 1:], z[:, :-1], out=tmp[:, 1:])
        torch.add(z[:, 0], z_gel, out=tmp[:, 0])
        refl.div_(tmp)
        # Masks as uint8, not bool: on CPU, comparisons into bool and bool -> float casts are
        # 2.4x and 8x slower than the same into uint8 (17 images, 1 thread).
        edge = _buf(ws, "edge", ct, torch.uint8)
        torch.ne(lab[:, 1:], lab[:, :-1], out=edge[:, 1:])
        torch.ne(lab[:, 0], GEL, out=edge[:, 0])
        h = ct.shape[1]
        near = _buf(ws, "near", ct, torch.uint8)
        near.copy_(edge)
        for d in range(1, min(k["ramp_rows"], h - 1) + 1):
            near[:, : h - d].bitwise_or_(edge[:, d:])
            near[:, d:].bitwise_or_(edge[:, : h - d])
        refl.mul_(tmp.copy_(near))  # tmp is free until the transmission term below
        # The partial-volume ramp spreads an interface's jump over about a CT voxel; summing
        # the partial reflections over ``interface_width`` gives back a sharp interface's |R|.
        rb = k["ramp_box"]
        if rb > 1:
            refl = _psf.blur_1d(refl, [1.0] * rb, -2, out=_buf(ws, "rbox", ct))
        # Incidence: the interface normal from the CT gradient (the CT is smooth where the label
        # map is a voxel staircase), on a grid of ~1 mm blocks (the resampled CT has no finer
        # detail): forward axial difference, lateral central difference of the two rows' sum;
        # cos = (|g_z| + eps) / (|g| + eps), so interfaces without CT contrast count as normal.
        kb = k["inc_block"]
        c = ct[:, ::kb, ::kb]
        b, h, w = ct.shape
        hb, wb = c.shape[1], c.shape[2]
        gz = ws.get("gz", (b, hb, wb), torch.float32)
        gs = ws.get("gs", (b, hb, wb), torch.float32)
        gx = ws.get("gxb", (b, hb, wb), torch.float32)
        torch.sub(c[:, 1:], c[:, :-1], out=gz[:, :-1])
        gz[:, -1] = 0.0
        torch.add(c[:, 1:], c[:, :-1], out=gs[:, :-1])
        gs[:, -1] = 2 * c[:, -1]
        gx.zero_()
        if wb > 2:
            torch.sub(gs[:, :, 2:], gs[:, :, :-2], out=gx[:, :, 1:-1])
        eps = m.incidence_eps * kb
        cos = torch.abs(gz, out=gs).add_(eps)
        cos.div_(gz.square_().addcmul_(gx, gx, value=0.0625).sqrt_().add_(eps))
        if m.incidence_exponent != 1.0:
            cos.pow_(m.incidence_exponent)
        if kb > 1:
            cos = cos.repeat_interleave(kb, dim=2)
        refl_v = refl.view(b, hb, kb, w)
        # Round-trip amplitude E, TGC included: exp(sum over rows above of (TGC rate -
        # 2 alpha f dz) + ln(1 - R^2)); transmission uses R before the incidence factor.
        q = z  # free now
        torch.index_select(k["gain_rate"], 0, flat_lab, out=q.view(-1))
        torch.mul(refl, refl, out=tmp).clamp_(max=1.0 - 1e-6).neg_().log1p_()
        q.add_(tmp, alpha=_LOG2_E / rb)
        e_amp = tmp  # exclusive cumulative sum: rows above only
        torch.cumsum(q[:, :-1], 1, out=e_amp[:, 1:])
        e_amp[:, 0] = 0.0
        bound = _MAX_LOG_AMPLITUDE * _LOG2_E
        exp2_(e_amp.clamp_(-bound, bound))
        refl_v.mul_(cos.view(b, hb, 1, w))
        refl.mul_(e_amp)
        # Complex scatterers T (1 + A_l V) (g_re + i g_im), attenuated, plus the reflections
        # (real), blurred by the PSF as one planar (re, im) field: every pass below reads
        # contiguous memory (interleaved pairs made |field|^2 2.1x and the multiply 4.7x slower
        # on CPU, 100 images, 1 thread)
        amp, bits = self._scatterers(lab12, geom, k, ws)
        amp.mul_(e_amp)
        b, h, w = ct.shape
        field = ws.get("field", (2, b, h, w), torch.float32)
        sel = _buf(ws, "hu_idx", ct, torch.int32).view(-1)  # free now
        torch.bitwise_right_shift(bits.view(-1), _LUT_BITS, out=sel).bitwise_and_(_PAIR_MASK)
        torch.index_select(self._gauss_pairs[0], 0, sel, out=field[0].view(-1))
        torch.index_select(self._gauss_pairs[1], 0, sel, out=field[1].view(-1))
        field.mul_(amp)
        field[0].add_(refl)
        scratch = ws.get("field_tmp", (2, b, h, w), torch.float32)
        _psf.blur_2d(field, *k["psf"], tmp=scratch)
        re, im = field[0], field[1]
        power = torch.mul(re, re, out=out).addcmul_(im, im)  # |field|^2 (complex abs is slow)
        if not display:
            power.sqrt_()
            return
        # 10 log10(power) + gain in dB, mapped from [-DR, 0] to [0, 1].
        # (log(0) = -inf clips to 0.)
        scale = 10.0 / math.log(10) / m.dynamic_range
        torch.add(1.0 + m.gain / m.dynamic_range, power.log_(), alpha=scale, out=power)
        power.clamp_(0.0, 1.0)
