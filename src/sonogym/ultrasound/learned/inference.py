"""The generator's inference form: ``FastGenerator``, a ``UNet`` prepared once for fast
evaluation (the simulator's default path; the ``UNet`` module itself is the reference).

What it changes against calling the module, and why (measurements: benchmarks/README.md,
"Learned ultrasound"):

* weights are cast once to the working precision (``float32`` or ``bfloat16``) and kept in
  channels-last layout, and activations stay in that precision and layout from layer to layer
  (but for the top level's: oneDNN answers the one-channel input in NCHW; forcing
  channels-last there gained nothing measurable).
  Under ``torch.autocast`` every convolution re-cast its float32 weights on every call, and
  oneDNN's channels-last kernels (transposed convolutions above all) are 2-3x faster than its
  NCHW ones here;
* instance normalisation (affine) stays channels-last: ``F.instance_norm`` reshapes its input
  to (1, B*C, H, W), i.e. copies a channels-last tensor to NCHW and back around every norm.
  Instance norm is group norm with one channel per group. On maps of at least
  ``GROUP_NORM_MIN_PIXELS`` pixels ATen's channels-last group norm is fast; it is called one
  image at a time, because it splits a call's pixels over the torch threads and a split that
  spans images would make an image depend on the others in its batch. On smaller maps (where
  that kernel walks memory with a stride of C) the per-channel means of x and x^2 come from
  float32 pooling, then one fused multiply-add. On other devices one batched group norm
  (its reductions are per image and channel). Statistics are float32 in both precisions;
* LeakyReLU and the residual sums run in place.

The layers, their order and their arithmetic are the module's: in float32 images match the
module's to a few 1e-6 (summation order), in bfloat16 to ~5e-4 on average (tests; the model card's
held-out figures are unchanged to 3 decimals, docs/learned.md). In bfloat16 an image does not
depend on the others in its batch, bit for bit; in float32 to ~1e-6 (oneDNN picks its
convolution kernels by batch size, for the module too). The group norm's statistics, like
oneDNN's float32 convolutions, depend on the number of torch threads in their last bits: the
same seed and thread count give the same images.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

from sonogym.ultrasound.learned.networks import ResidualUnit, UNet, UpBlock

PRECISIONS = ("float32", "bfloat16")
#: what ``resolve_precision`` accepts besides ``PRECISIONS``
AUTO = "auto"
_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
#: /proc/cpuinfo flags of CPUs that compute in bfloat16 natively (elsewhere it is emulated, slow)
_NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")


@functools.cache
def native_bfloat16() -> bool:
    """Whether this machine's CPU has bfloat16 instructions (AVX-512 BF16 or AMX)."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((ln.split(":", 1)[1].split() for ln in f if ln.startswith("flags")), [])
    except OSError:
        return False
    return any(flag in flags for flag in _NATIVE_BF16_FLAGS)


def resolve_precision(precision: str, what: str = "precision") -> str:
    """The working precision ``precision`` names: "auto" is bfloat16 on a CPU with native
    bfloat16 (images bounded against float32 and the model card's figures unchanged:
    docs/learned.md), float32 elsewhere; "float32" and "bfloat16" name themselves."""
    if precision == AUTO:
        return "bfloat16" if native_bfloat16() else "float32"
    if precision not in PRECISIONS:
        raise ValueError(f"{what} must be one of {(AUTO, *PRECISIONS)}, got {precision!r}")
    return precision


#: Pixels per map from which ATen's channels-last group norm takes its contiguous path (its
#: threshold, ``feature_map_threshold`` in GroupNormKernel.cpp); below, pooled statistics.
GROUP_NORM_MIN_PIXELS = 1024
_SLOPE = 0.2  # LeakyReLU's, as in networks._norm_act
_CL = torch.channels_last


class _Conv:
    """A convolution's (transposed or not) weights in the working precision and layout."""

    def __init__(self, conv: torch.nn.Conv2d | torch.nn.ConvTranspose2d, dtype) -> None:
        self.weight = conv.weight.detach().to(dtype).contiguous(memory_format=_CL)
        self.bias = None if conv.bias is None else conv.bias.detach().to(dtype)
        self.stride, self.padding = conv.stride, conv.padding
        self.transposed = isinstance(conv, torch.nn.ConvTranspose2d)
        self.output_padding = getattr(conv, "output_padding", 0)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self.transposed:
            return F.conv_transpose2d(
                x, self.weight, self.bias, self.stride, self.padding, self.output_padding
            )
        return F.conv2d(x, self.weight, self.bias, self.stride, self.padding)


class _NormAct:
    """InstanceNorm2d(affine) + LeakyReLU(0.2) of a channels-last tensor (module docstring)."""

    def __init__(self, norm: torch.nn.InstanceNorm2d) -> None:
        self.weight = norm.weight.detach().float()
        self.bias = norm.bias.detach().float()
        self.eps = float(norm.eps)

    def __call__(self, y: torch.Tensor) -> torch.Tensor:
        b, c, h, w = y.shape
        if y.device.type != "cpu":  # a reduction per image and channel: batch independent
            y = F.group_norm(y, c, self.weight, self.bias, self.eps)
        elif h * w >= GROUP_NORM_MIN_PIXELS:
            # one image per call: ATen's CPU group norm splits a call's pixels over the torch
            # threads, and a split across images would make an image depend on the batch
            y = torch.cat(
                [F.group_norm(y[i : i + 1], c, self.weight, self.bias, self.eps) for i in range(b)]
            )
        else:
            yf = y.float()
            mean = F.adaptive_avg_pool2d(yf, 1)
            var = (F.adaptive_avg_pool2d(yf * yf, 1) - mean * mean).clamp_(min=0)
            scale = self.weight.view(1, c, 1, 1) * torch.rsqrt(var + self.eps)
            shift = self.bias.view(1, c, 1, 1) - mean * scale
            y = torch.addcmul(shift.to(y.dtype), y, scale.to(y.dtype))
        return F.leaky_relu_(y, _SLOPE)


class _Residual:
    def __init__(self, unit: ResidualUnit, dtype) -> None:
        self.conv = _Conv(unit.conv[0], dtype)
        self.norm_act = _NormAct(unit.conv[1])
        self.skip = None if isinstance(unit.skip, torch.nn.Identity) else _Conv(unit.skip, dtype)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        y = self.norm_act(self.conv(x))
        return y.add_(x if self.skip is None else self.skip(x))


class _Up:
    def __init__(self, block: UpBlock, dtype) -> None:
        self.up = _Conv(block.up[0], dtype)
        self.norm_act = _NormAct(block.up[1])
        out = block.out
        self.out = _Residual(out, dtype) if isinstance(out, ResidualUnit) else _Conv(out, dtype)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.norm_act(self.up(x)))


class FastGenerator:
    """A ``UNet``'s forward pass for inference in ``precision`` ("float32" or "bfloat16"):
    (B, C_in, H, W) input -> (B, C_out, H, W) float32 in (0, 1), as ``gen(x)``. Holds its
    own copy of the weights: later changes to ``gen`` are not seen."""

    def __init__(self, gen: UNet, precision: str = "float32") -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        self.precision = precision
        self.dtype = _DTYPES[precision]
        self.factor = gen.factor
        self.downs = [_Residual(d, self.dtype) for d in gen.downs]
        self.bottom = _Residual(gen.bottom, self.dtype)
        self.ups = [_Up(u, self.dtype) for u in gen.ups]

    @torch.no_grad()
    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % self.factor or w % self.factor:
            raise ValueError(f"UNet input {h}x{w} must be divisible by {self.factor}")
        x = x.to(self.dtype).contiguous(memory_format=_CL)
        skips = []
        for down in self.downs:
            x = down(x)
            skips.append(x)
        x = self.bottom(x)
        for i in reversed(range(len(self.ups))):
            x = self.ups[i](torch.cat([skips[i], x], 1))
        return torch.sigmoid(x.float()).contiguous()
