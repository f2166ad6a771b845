"""Imaging randomisation for training: per-episode display settings a sonographer turns and
attenuation a patient brings, so a policy does not learn one machine's brightness.

Each env draws, at each episode reset, one setting of every knob below (uniform in its range,
from the env's seeded generator); the image of that episode is displayed with it:

* ``gain_db``: gain added before the display mapping (dB);
* ``dynamic_range_db``: the dB range mapped onto [0, 1] (the ``physical`` model's is 60);
* ``tgc_db``: the time-gain-compensation curve an operator sets: a gain at each of
  ``TGC_KNOTS`` depths (top, middle, bottom of the image), linear in between (dB);
* ``attenuation_db_per_cm``: round-trip attenuation the TGC does not compensate (a patient whose
  tissue attenuates more or less than the ``physical`` model's 0.6 dB/cm/MHz: at 3.5 MHz,
  0.2 dB/cm/MHz more is 1.4 dB per cm of depth);
* ``speckle_blur``: a coarser speckle grain: the envelope blended with its Gaussian smoothing
  (sigma ``SPECKLE_SIGMA``) by this weight (0 keeps the simulated grain);
* ``depth``: imaging depth (m) shown over the image's rows, at most the probe's depth: the
  image is the top ``depth`` of the simulated one stretched over all rows (a shallower depth
  setting).

With the ``physical`` model the settings act on the TGC-compensated envelope before log
compression (``ModelBasedSimulator.simulate_raw``), exactly as on a scanner. With other
simulators (the ``sonogym`` model, the learned nets) they act on the display image read as a
60 dB log display (dB = (y - 1) * 60); pixels at the display's floor stay there.

Evaluation never randomises (envs default to ``imaging_randomization=False``), and neither do
the training presets: a run asks for it with ``--env-option imaging_randomization=true``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from sonogym.ultrasound import psf as _psf
from sonogym.ultrasound.probe import ProbeGeometry

#: Relative depths (0 = probe face, 1 = the image's last row) of the TGC curve's knots.
TGC_KNOTS = (0.0, 0.5, 1.0)
#: m, sigma of the smoothing that ``speckle_blur`` blends in (about the speckle grain's size).
SPECKLE_SIGMA = 0.6e-3
#: dB the display of a non-``physical`` simulator is read as spanning.
NOMINAL_DYNAMIC_RANGE = 60.0


@dataclass(frozen=True)
class ImagingRandomization:
    """Ranges (low, high) of the per-episode imaging settings, drawn uniformly (module doc)."""

    gain_db: tuple[float, float] = (-6.0, 6.0)  # dB
    dynamic_range_db: tuple[float, float] = (50.0, 70.0)  # dB
    tgc_db: tuple[float, float] = (-4.0, 4.0)  # dB, at each TGC knot
    attenuation_db_per_cm: tuple[float, float] = (-1.5, 1.5)  # dB per cm of depth, round trip
    speckle_blur: tuple[float, float] = (0.0, 0.6)  # weight of the smoothed envelope
    depth: tuple[float, float] = (0.08, 0.10)  # m, imaging depth shown

    def __post_init__(self) -> None:
        for f in fields(self):
            lo, hi = (float(v) for v in getattr(self, f.name))
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ValueError(f"imaging randomisation {f.name}: need finite low <= high, got "
                                 f"{getattr(self, f.name)!r}")  # fmt: skip
            object.__setattr__(self, f.name, (lo, hi))
        if self.dynamic_range_db[0] <= 0 or self.depth[0] <= 0:
            raise ValueError("imaging randomisation: dynamic_range_db and depth must be > 0")
        if not (0 <= self.speckle_blur[0] and self.speckle_blur[1] <= 1):
            raise ValueError("imaging randomisation: speckle_blur is a weight within [0, 1]")

    #: Columns of a draw (``ImagingSettings.values``), in order.
    COLUMNS = ("gain_db", "dynamic_range_db", "tgc_db", "tgc_db", "tgc_db",
               "attenuation_db_per_cm", "speckle_blur", "depth")  # fmt: skip

    def draw(self, u: torch.Tensor) -> torch.Tensor:
        """Settings (K, 8) from uniforms ``u`` (K, 8) in [0, 1): gain, dynamic range, the three
        TGC knots, attenuation slope, speckle blur, depth (units as the fields)."""
        lo = torch.tensor([getattr(self, c)[0] for c in self.COLUMNS], dtype=u.dtype,
                          device=u.device)  # fmt: skip
        hi = torch.tensor([getattr(self, c)[1] for c in self.COLUMNS], dtype=u.dtype,
                          device=u.device)  # fmt: skip
        return lo + (hi - lo) * u


def imaging_ranges(value) -> ImagingRandomization | None:
    """A config's ``imaging_randomization`` as ranges: False/None -> None (image as simulated),
    True -> the documented ranges, a dict (a config read back from JSON) or an
    ``ImagingRandomization`` -> those ranges."""
    if value is None or value is False:
        return None
    if value is True:
        return ImagingRandomization()
    if isinstance(value, ImagingRandomization):
        return value
    if isinstance(value, dict):
        names = {f.name for f in fields(ImagingRandomization)}
        unknown = sorted(set(value) - names)
        if unknown:
            raise ValueError(
                f"imaging_randomization: unknown settings {unknown}; known {sorted(names)}"
            )
        return ImagingRandomization(**{k: tuple(v) for k, v in value.items()})
    raise ValueError(
        f"imaging_randomization must be true/false or sonogym.ultrasound.randomization."
        f"ImagingRandomization ranges, got {value!r}"
    )


def nominal(n: int, probe: ProbeGeometry, dynamic_range: float, device=None) -> torch.Tensor:
    """(n, 8) settings that reproduce the simulator's own display: 0 dB gain, the simulator's
    dynamic range, flat TGC, no extra attenuation, no blur, the probe's full depth."""
    row = [0.0, dynamic_range, 0.0, 0.0, 0.0, 0.0, 0.0, probe.depth]
    return torch.tensor(row, dtype=torch.float32, device=device).repeat(n, 1)


def randomized_display(
    envelope: torch.Tensor,
    settings: torch.Tensor,
    probe: ProbeGeometry,
    gain_db: float = 0.0,
) -> torch.Tensor:
    """Display images (N, E, H, W) in [0, 1] from TGC-compensated envelopes (the ``physical``
    model's ``simulate_raw``) with per-image ``settings`` (N, 8): the scanner's mapping
    y = clamp(1 + (20 log10 envelope + gain + TGC(d) - attenuation d) / DR, 0, 1) after the
    speckle blend, then the depth zoom. ``gain_db``: the model's own gain."""
    env = _blend_speckle(envelope, settings[:, 6], probe)
    db = 20.0 * torch.log10(env.clamp_min(1e-30))
    return _finish(db + gain_db, settings, probe)


def randomized_from_display(
    image: torch.Tensor, settings: torch.Tensor, probe: ProbeGeometry
) -> torch.Tensor:
    """The same settings on display images in [0, 1] of a simulator without an envelope (read as
    a ``NOMINAL_DYNAMIC_RANGE`` log display; floor pixels stay at the floor)."""
    floor = image <= 0
    img = _blend_speckle(image, settings[:, 6], probe)
    db = (img - 1.0) * NOMINAL_DYNAMIC_RANGE
    out = _finish(db, settings, probe, floor=floor)
    return out


def _blend_speckle(x: torch.Tensor, weight: torch.Tensor, probe: ProbeGeometry) -> torch.Tensor:
    """``x`` blended with its Gaussian smoothing by ``weight`` (N,) per image."""
    n, e, h, w = x.shape

    def taps(spacing: float) -> list[float]:
        g = _psf.gaussian_taps(SPECKLE_SIGMA, spacing, 2 * SPECKLE_SIGMA)
        return _psf.scaled(g, 1.0)  # keeps the mean brightness

    flat = x.reshape(n * e, h, w)
    smooth = _psf.blur_2d(flat, taps(probe.depth_spacing), taps(probe.width_spacing))
    wgt = weight.to(x.dtype).repeat_interleave(e).view(-1, 1, 1)
    return torch.lerp(flat, smooth, wgt).view(n, e, h, w)


def _finish(db: torch.Tensor, s: torch.Tensor, probe: ProbeGeometry, floor=None) -> torch.Tensor:
    """dB image (N, E, H, W) -> display in [0, 1] with gain, TGC, attenuation, range, depth."""
    n, e, h, w = db.shape
    rel = torch.linspace(0.0, 1.0, h, device=db.device, dtype=db.dtype)  # row / (H - 1)
    depth_cm = rel * (h - 1) * probe.depth_spacing * 1e2
    knots = torch.tensor(TGC_KNOTS, device=db.device, dtype=db.dtype)
    tgc = _interp_rows(rel, knots, s[:, 2:5].to(db.dtype))  # (N, H)
    ramp = s[:, 0:1] + tgc - s[:, 5:6] * depth_cm  # (N, H) dB added per row
    y = (1.0 + (db + ramp[:, None, :, None]) / s[:, 1].view(n, 1, 1, 1)).clamp_(0.0, 1.0)
    if floor is not None:
        y = y.masked_fill(floor, 0.0)
    return _zoom_depth(y, (s[:, 7] / probe.depth).clamp(max=1.0))


def _interp_rows(rel: torch.Tensor, knots: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear curve through (knots, values (N, K)) at ``rel`` (H,) -> (N, H)."""
    i = torch.searchsorted(knots, rel, right=True).clamp(1, len(knots) - 1)
    x0, x1 = knots[i - 1], knots[i]
    t = ((rel - x0) / (x1 - x0)).clamp(0, 1)
    return values[:, i - 1] * (1 - t) + values[:, i] * t


def _zoom_depth(y: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Row r of each image shows source row r * scale (linear), scale (N,) in (0, 1]."""
    n, e, h, w = y.shape
    src = torch.arange(h, device=y.device, dtype=y.dtype)[None] * scale[:, None].to(y.dtype)
    i0 = src.floor().long().clamp_(0, h - 1)
    i1 = (i0 + 1).clamp_(max=h - 1)
    t = (src - i0.to(y.dtype)).view(n, 1, h, 1)
    a = torch.gather(y, 2, i0.view(n, 1, h, 1).expand(n, e, h, w))
    b = torch.gather(y, 2, i1.view(n, 1, h, 1).expand(n, e, h, w))
    return torch.lerp(a, b, t)
