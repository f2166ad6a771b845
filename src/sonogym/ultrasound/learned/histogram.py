"""Batched CDF histogram matching of CT slices to a reference (training) CT distribution.

The paper matches the intensity histogram of input CT slices to that of the training CT to
narrow the domain gap. ``HistogramReference.fit`` windows reference CT (HU) to [0, 1]
(``CT_WINDOW_HU``, the paper's range) and stores a ``bins``-bin histogram's edges and CDF.
``match`` builds, per image or per batch, the source CDF at the same bin edges, maps every edge
through the reference's inverse CDF (``searchsorted`` + linear interpolation within a bin) and
passes pixels through that look-up table (linear within a bin). Everything is torch and runs on
the input's device.
"""

from __future__ import annotations

import torch

#: The paper's CT range: [0, 150] on the reference's 0..255 scale ~ HU [-300, 1641].
CT_WINDOW_HU: tuple[float, float] = (-300.0, 1641.0)


def window_ct(ct_hu: torch.Tensor, window: tuple[float, float] = CT_WINDOW_HU) -> torch.Tensor:
    """HU -> [0, 1], clamped to the window."""
    lo, hi = window
    return ((ct_hu.float() - lo) / (hi - lo)).clamp_(0.0, 1.0)


def _cdf_at_edges(x: torch.Tensor, bins: int) -> torch.Tensor:
    """x: (B, P) in [0, 1] -> (B, bins + 1) CDF at the bin edges (0 at edge 0, 1 at the last)."""
    idx = (x * bins).long().clamp_(0, bins - 1)
    counts = torch.zeros(x.shape[0], bins, device=x.device, dtype=torch.float32)
    counts.scatter_add_(1, idx, torch.ones_like(x, dtype=torch.float32))
    cdf = counts.cumsum(1) / counts.sum(1, keepdim=True).clamp_min(1)
    return torch.cat([torch.zeros_like(cdf[:, :1]), cdf], 1)


class HistogramReference:
    """Reference distribution (bin edges + CDF) of windowed training CT, and the matcher."""

    def __init__(self, cdf: torch.Tensor, window: tuple[float, float] = CT_WINDOW_HU) -> None:
        cdf = torch.as_tensor(cdf, dtype=torch.float32).flatten()
        if cdf.numel() < 3 or abs(float(cdf[0])) > 1e-6 or abs(float(cdf[-1]) - 1) > 1e-4:
            raise ValueError("reference CDF must run from 0 to 1 at bins + 1 edges")
        self.cdf = cdf
        self.bins = cdf.numel() - 1
        self.edges = torch.linspace(0.0, 1.0, self.bins + 1)
        self.window = (float(window[0]), float(window[1]))

    @classmethod
    def fit(
        cls, ct_hu: torch.Tensor, bins: int = 256, window: tuple[float, float] = CT_WINDOW_HU
    ) -> HistogramReference:
        """Reference from CT samples in HU (any shape)."""
        x = window_ct(torch.as_tensor(ct_hu), window).reshape(1, -1)
        return cls(_cdf_at_edges(x, bins)[0].cpu(), window)

    @classmethod
    def fit_windowed(
        cls, x: torch.Tensor, bins: int = 256, window: tuple[float, float] = CT_WINDOW_HU
    ) -> HistogramReference:
        """Reference from CT already windowed to [0, 1] with ``window``."""
        return cls(_cdf_at_edges(x.reshape(1, -1).float(), bins)[0].cpu(), window)

    def state_dict(self) -> dict:
        return {"cdf": self.cdf.clone(), "window": list(self.window)}

    @classmethod
    def from_state_dict(cls, d: dict) -> HistogramReference:
        return cls(d["cdf"], tuple(d["window"]))

    def inverse_cdf(self, u: torch.Tensor) -> torch.Tensor:
        """Reference quantile function at levels u (any shape, in [0, 1])."""
        cdf, edges = self.cdf.to(u.device), self.edges.to(u.device)
        j = torch.searchsorted(cdf, u.contiguous(), right=False).clamp_(1, self.bins)
        c0, c1 = cdf[j - 1], cdf[j]
        frac = ((u - c0) / (c1 - c0).clamp_min(1e-12)).clamp_(0, 1)
        return edges[j - 1] + frac * (edges[j] - edges[j - 1])

    def lut(self, x: torch.Tensor, per_image: bool = False) -> torch.Tensor:
        """LUT (B or 1, bins + 1) mapping x's bin edges (x: (B, ...) windowed CT in [0, 1])."""
        flat = x.reshape(x.shape[0], -1) if per_image else x.reshape(1, -1)
        return self.inverse_cdf(_cdf_at_edges(flat, self.bins))

    def apply(self, x: torch.Tensor, lut: torch.Tensor) -> torch.Tensor:
        """Pass windowed CT x (B, ...) through a LUT from :meth:`lut` (linear within bins)."""
        b = x.shape[0]
        flat = x.reshape(b, -1)
        pos = flat.clamp(0, 1) * self.bins
        i = pos.floor().long().clamp_(0, self.bins - 1)
        frac = pos - i
        lut = lut.expand(b, -1)
        lo, hi = lut.gather(1, i), lut.gather(1, i + 1)
        return (lo + frac * (hi - lo)).reshape(x.shape)

    def match(self, x: torch.Tensor, per_image: bool = False) -> torch.Tensor:
        """Windowed CT x (B, ...) in [0, 1] -> same shape, histogram matched to the reference
        (one LUT for the batch, or one per image)."""
        return self.apply(x, self.lut(x, per_image))
