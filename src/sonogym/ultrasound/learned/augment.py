"""Down/up-sampling of the CT input (the paper's augmentation for unseen CT resolutions)."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def down_up(x: torch.Tensor, factor: float) -> torch.Tensor:
    """(B, C, H, W): nearest-exact down-sampling by ``factor``, bilinear back to (H, W).

    ``factor=4`` on 256 x 256 is the reference simulator's deterministic 64 x 64 degradation.
    """
    if factor <= 1:
        return x
    h, w = x.shape[-2:]
    small = F.interpolate(
        x, size=(max(1, round(h / factor)), max(1, round(w / factor))), mode="nearest-exact"
    )
    return F.interpolate(small, size=(h, w), mode="bilinear", align_corners=False)


def random_down_up(
    x: torch.Tensor,
    generator: torch.Generator | None = None,
    factors: tuple[float, ...] = (1.0, 2.0, 3.0, 4.0),
    p: float = 0.8,
) -> torch.Tensor:
    """Per sample, with probability p, degrade by a factor drawn from ``factors`` (else keep).

    Batched: one interpolation per distinct factor. Shape and device are preserved.
    """
    b = x.shape[0]
    dev = generator.device if generator is not None else torch.device("cpu")
    apply = torch.rand(b, generator=generator, device=dev) < p
    pick = torch.randint(len(factors), (b,), generator=generator, device=dev)
    pick = torch.where(apply, pick, torch.full_like(pick, -1)).to(x.device)
    out = x.clone()
    for k, f in enumerate(factors):
        sel = (pick == k).nonzero().flatten()
        if f > 1 and sel.numel():
            out[sel] = down_up(x[sel], f)
    return out
