"""Image encoders of the IL policies (torch only, no torchvision, no pretrained weights).

* ``ResNetEncoder``: a ResNet-style trunk (7x7/2 stem, 3x3/2 max-pool, stages of basic
  residual blocks, stride 2 from the second stage on; output stride 32 for four stages). With
  widths (64, 128, 256, 512) and two blocks per stage it is ResNet-18's trunk without the
  classifier (what LeRobot's ACT and Diffusion Policy use); smaller widths and one block per
  stage make the cpu sizes. Norm: GroupNorm with channels / 16 groups (LeRobot's
  ``use_group_norm`` replacement) or BatchNorm.
* ``SpatialSoftmax``: Diffusion Policy's keypoint pooling: a 1x1 conv to K maps, a softmax
  over each map's pixels and the expected (x, y) in [-1, 1] of each: (B, K, 2).
* ``sine_position_2d`` / ``sine_position_1d``: DETR's fixed sinusoidal position embeddings
  (ACT's image-token and VAE-encoder positions).
* ``crop``: centre or per-sample random crops (Diffusion Policy's augmentation).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def make_norm(kind: str, channels: int) -> nn.Module:
    if kind == "group":
        return nn.GroupNorm(max(1, channels // 16), channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    raise ValueError(f"norm must be 'group' or 'batch', got {kind!r}")


class BasicBlock(nn.Module):
    """Two 3x3 convs with a residual connection (1x1 projection when the shape changes)."""

    def __init__(self, c_in: int, c_out: int, stride: int, norm: str) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False)
        self.n1 = make_norm(norm, c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False)
        self.n2 = make_norm(norm, c_out)
        self.skip = (
            nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), make_norm(norm, c_out))
            if stride != 1 or c_in != c_out
            else nn.Identity()
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.n1(self.conv1(x)))
        return F.relu(self.n2(self.conv2(y)) + self.skip(x))


class ResNetEncoder(nn.Module):
    """(B, C_in, H, W) -> (B, widths[-1], H', W'); see the module doc."""

    def __init__(
        self, in_channels: int, widths: tuple[int, ...], blocks: tuple[int, ...], norm: str
    ) -> None:
        super().__init__()
        if len(widths) != len(blocks) or not widths or min(blocks) < 1:
            raise ValueError(f"widths {widths} and blocks {blocks}: same non-zero length, >= 1")
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, widths[0], 7, 2, 3, bias=False),
            make_norm(norm, widths[0]),
            nn.ReLU(),
            nn.MaxPool2d(3, 2, 1),
        )
        layers = []
        c = widths[0]
        for i, (w, n) in enumerate(zip(widths, blocks, strict=True)):
            for j in range(n):
                layers.append(BasicBlock(c, w, 2 if (i > 0 and j == 0) else 1, norm))
                c = w
        self.stages = nn.Sequential(*layers)
        self.out_channels = c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.stages(self.stem(x))

    def out_shape(self, c: int, h: int, w: int) -> tuple[int, int, int]:
        """(C', H', W') of the output for a (c, h, w) input."""
        with torch.no_grad():
            dev = next(self.parameters()).device
            return tuple(self(torch.zeros(1, c, h, w, device=dev)).shape[1:])


class SpatialSoftmax(nn.Module):
    """(B, C, H, W) -> (B, K, 2) expected keypoint coordinates (x, y) in [-1, 1]."""

    def __init__(self, in_channels: int, h: int, w: int, num_keypoints: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(in_channels, num_keypoints, 1)
        ys, xs = torch.meshgrid(
            torch.linspace(-1.0, 1.0, h), torch.linspace(-1.0, 1.0, w), indexing="ij"
        )
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1))
        self.num_keypoints = num_keypoints

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a = self.proj(x).flatten(2)  # (B, K, H W)
        return torch.softmax(a, dim=-1) @ self.grid


def sine_position_1d(n: int, dim: int) -> torch.Tensor:
    """(n, dim) fixed sinusoidal embedding: sin on even, cos on odd channels."""
    pos = torch.arange(n, dtype=torch.float64)[:, None]
    freq = torch.pow(10000.0, 2 * (torch.arange(dim) // 2) / dim)[None]
    ang = pos / freq
    out = torch.where(torch.arange(dim) % 2 == 0, ang.sin(), ang.cos())
    return out.float()


def sine_position_2d(h: int, w: int, dim: int) -> torch.Tensor:
    """(dim, h, w) DETR sine embedding: dim / 2 channels encode the row, dim / 2 the column,
    positions normalised to (0, 2 pi]."""
    if dim % 4:
        raise ValueError(f"dim must be a multiple of 4, got {dim}")
    half = dim // 2
    y = torch.arange(1, h + 1, dtype=torch.float64) / (h + 1e-6) * 2 * math.pi
    x = torch.arange(1, w + 1, dtype=torch.float64) / (w + 1e-6) * 2 * math.pi
    freq = torch.pow(10000.0, 2 * (torch.arange(half) // 2) / half)
    py, px = y[:, None] / freq, x[:, None] / freq  # (h, half), (w, half)
    even = torch.arange(half) % 2 == 0
    py = torch.where(even, py.sin(), py.cos())
    px = torch.where(even, px.sin(), px.cos())
    out = torch.cat([py[:, None, :].expand(h, w, half), px[None, :, :].expand(h, w, half)], dim=-1)
    return out.permute(2, 0, 1).float()


def crop(x: torch.Tensor, size: tuple[int, int], generator: torch.Generator | None) -> torch.Tensor:
    """Crop (B, C, H, W) to ``size``: random offsets per sample with ``generator``, centre
    crop without."""
    b, _, h, w = x.shape
    ch, cw = size
    if (ch, cw) == (h, w):
        return x
    if ch > h or cw > w:
        raise ValueError(f"crop {size} larger than the image ({h}, {w})")
    if generator is None:
        top, left = (h - ch) // 2, (w - cw) // 2
        return x[:, :, top : top + ch, left : left + cw]
    top = torch.randint(0, h - ch + 1, (b,), generator=generator, device=generator.device)
    left = torch.randint(0, w - cw + 1, (b,), generator=generator, device=generator.device)
    rows = (top.to(x.device)[:, None] + torch.arange(ch, device=x.device))[:, None, :, None]
    cols = (left.to(x.device)[:, None] + torch.arange(cw, device=x.device))[:, None, None, :]
    bi = torch.arange(b, device=x.device)[:, None, None, None]
    ci = torch.arange(x.shape[1], device=x.device)[None, :, None, None]
    return x[bi, ci, rows, cols]


def resize(x: torch.Tensor, size: tuple[int, int] | None) -> torch.Tensor:
    """Area-resample (B, C, H, W) images to ``size`` (H, W); None or the same size: unchanged."""
    if size is None or tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=tuple(size), mode="area")
