"""pix2pix networks: a residual U-Net generator and a PatchGAN discriminator.

Generator (after the paper's U-Net figure and the reference's MONAI ``UNet``: instance norm,
LeakyReLU(0.2), kernel 3, one residual unit per level, stride-2 down/up sampling, skip
connections by concatenation). ``channels`` lists the encoder widths; every entry but the last
halves the resolution, the last is the bottleneck (stride 1). The paper/reference uses
(64, 128, 512, 512, 512, 512, 512) on 256 x 256 inputs; our default (16, 32, 64, 128, 128) is a
smaller net (~0.6 M parameters) that trains on a CPU. Inputs must be divisible by
2 ** (len(channels) - 1). The output goes through a sigmoid, so it is in (0, 1) (the reference
has no output activation and relies on training to stay near [0, 1]).

Discriminator: the pix2pix ``NLayerDiscriminator`` (4 x 4 convs, stride 2, widths doubling up
to 8x, instance norm; ``n_layers=3`` gives 70 x 70 receptive fields) on the concatenated
(CT, US) pair; it returns a map of patch logits.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn


def _norm_act(c: int) -> list[nn.Module]:
    return [nn.InstanceNorm2d(c, affine=True), nn.LeakyReLU(0.2)]


class ResidualUnit(nn.Module):
    """conv3x3(stride) -> IN -> LeakyReLU, plus a (strided) projection of the input."""

    def __init__(self, cin: int, cout: int, stride: int = 1) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), *_norm_act(cout))
        if stride == 1 and cin == cout:
            self.skip: nn.Module = nn.Identity()
        else:
            k = 3 if stride != 1 else 1
            self.skip = nn.Conv2d(cin, cout, k, stride, k // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x) + self.skip(x)


class UpBlock(nn.Module):
    """Transposed conv3x3 stride 2 -> IN -> LeakyReLU, then a residual unit (or, at the top,
    a 1x1 conv to the output channels)."""

    def __init__(self, cin: int, cout: int, top: bool) -> None:
        super().__init__()
        mid = cout if not top else max(cin // 2, 8)
        self.up = nn.Sequential(
            nn.ConvTranspose2d(cin, mid, 3, 2, 1, output_padding=1), *_norm_act(mid)
        )
        self.out = nn.Conv2d(mid, cout, 1) if top else ResidualUnit(mid, cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.up(x))


@dataclass(frozen=True)
class UNetConfig:
    channels: tuple[int, ...] = (16, 32, 64, 128, 128)
    in_channels: int = 1
    out_channels: int = 1

    @classmethod
    def from_width(cls, width: int = 16, depth: int = 4, max_mult: int = 8) -> UNetConfig:
        """Widths width * 2**i (capped at width * max_mult) for ``depth`` down steps."""
        ch = [width * min(2**i, max_mult) for i in range(depth)]
        return cls(channels=tuple(ch + [ch[-1]]))

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> UNetConfig:
        return cls(**{**d, "channels": tuple(d["channels"])})


class UNet(nn.Module):
    """Residual U-Net generator; (B, 1, H, W) CT in [0, 1] -> (B, 1, H, W) US in (0, 1)."""

    def __init__(self, config: UNetConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or UNetConfig()
        ch = list(config.channels)
        if len(ch) < 2:
            raise ValueError("UNet needs at least two channel entries (one down step + bottom)")
        k = len(ch) - 1
        self.factor = 2**k
        cins = [config.in_channels] + ch[:-2]
        self.downs = nn.ModuleList(ResidualUnit(cins[i], ch[i], 2) for i in range(k))
        self.bottom = ResidualUnit(ch[k - 1], ch[k], 1)
        ups = []
        for i in range(k):  # i = level, 0 on top
            cin = ch[i] + (ch[k] if i == k - 1 else ch[i])
            cout = config.out_channels if i == 0 else ch[i - 1]
            ups.append(UpBlock(cin, cout, top=i == 0))
        self.ups = nn.ModuleList(ups)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % self.factor or w % self.factor:
            raise ValueError(f"UNet input {h}x{w} must be divisible by {self.factor}")
        skips = []
        for d in self.downs:
            x = d(x)
            skips.append(x)
        x = self.bottom(x)
        for i in reversed(range(len(self.ups))):
            x = self.ups[i](torch.cat([skips[i], x], 1))
        return torch.sigmoid(x)


class PatchDiscriminator(nn.Module):
    """pix2pix PatchGAN on (CT, US) pairs; returns (B, 1, h, w) logits."""

    def __init__(self, in_channels: int = 2, width: int = 64, n_layers: int = 3) -> None:
        super().__init__()
        layers: list[nn.Module] = [nn.Conv2d(in_channels, width, 4, 2, 1), nn.LeakyReLU(0.2)]
        c = width
        for i in range(1, n_layers + 1):
            c_next = width * min(2**i, 8)
            stride = 2 if i < n_layers else 1
            layers += [nn.Conv2d(c, c_next, 4, stride, 1), *_norm_act(c_next)]
            c = c_next
        layers.append(nn.Conv2d(c, 1, 4, 1, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, ct: torch.Tensor, us: torch.Tensor) -> torch.Tensor:
        return self.net(torch.cat([ct, us], 1))
