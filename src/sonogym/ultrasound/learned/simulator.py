"""``LearnedSimulator``: pix2pix generators behind the ``UltrasoundSimulator`` interface.

Per call, on the N x E slices (batched, in chunks of ``batch_size`` images):
1. window the CT (HU) to [0, 1] with the net's window (the paper's range by default);
2. resize bilinearly to the net's input size (that of its training pairs);
3. optionally degrade by down/up-sampling (``degrade``; the reference uses 4 on 256 x 256);
4. histogram-match to the net's training CT (``histogram``):
   * ``"first_batch"`` (default, the reference's behaviour): one population-level LUT, fitted
     by :meth:`LearnedSimulator.fit_source` on a CT sample (e.g. the patients' volumes or a
     batch of slices) or else from the first call's batch, then reused, so images are
     deterministic and batch independent from then on. Training inputs are matched per batch,
     i.e. at population level too;
   * ``"per_image"``: one LUT per image (batch independent from the first call, but every
     image gets the training histogram, so a slice without bone is stretched until some of it
     reads as bone: use with care);
   * ``"none"``: no matching;
5. run the generator (output in (0, 1), sigmoid), resize back, multiply by ``output_scale``
   (1; the reference's env used 0.1) and clamp to [0, 1].

With several nets, by default one net serves the whole batch and a new one is drawn uniformly
(seeded generator) every ``change_interval`` calls (the reference: 100); ``simulate(slices,
nets=...)`` instead gives each env its own net (the envs draw one per env at every episode reset,
see ``sonogym.envs.imaging``).

Geometry: a net is applied to the slice's whole field of view, resized to its input grid. It
was trained on pairs of ``image_size`` pixels at ``pixel_spacing_m`` (checkpoint fields), so the
slice's field of view (rows x depth spacing, columns x width spacing) should match that of the
training pairs; a mismatch over 10 % is warned about once (the image would be stretched).
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F

from sonogym.ultrasound.learned.augment import down_up
from sonogym.ultrasound.learned.checkpoint import load_generator
from sonogym.ultrasound.learned.histogram import window_ct
from sonogym.ultrasound.slicer import Slices

HISTOGRAM_MODES = ("per_image", "first_batch", "none")
PRECISIONS = ("float32", "bfloat16")


class LearnedSimulator:
    """Learning-based ultrasound simulator (``UltrasoundSimulator`` protocol).

    Args:
        weights: one or several ``generator.pt`` files written by ``sonogym lb-train``.
        device: where the nets run; slices on other devices are moved and the images moved
            back.
        seed: seed of the random net choice.
        change_interval: calls between two random net draws.
        histogram: "per_image", "first_batch" or "none" (see the module docstring).
        degrade: deterministic down/up-sampling factor applied before matching (1 = none).
        output_scale: factor on the generator's output.
        batch_size: images per forward pass (None: 16 on CPU, where small chunks stay in
            cache and run ~20 % faster than one big batch, 256 elsewhere).
        precision: "float32" (default) or "bfloat16": the generator's convolutions under
            autocast in bfloat16 (the generator ~3x, a whole ``simulate`` 1.6-2.1x faster on
            CPUs with AVX-512 BF16; images differ from float32 by ~1e-3 on average, see
            docs/envs.md). Inputs, normalisation and outputs stay float32.
    """

    def __init__(
        self,
        weights: str | Path | Sequence[str | Path],
        device: torch.device | str = "cpu",
        seed: int = 0,
        change_interval: int = 100,
        histogram: str = "first_batch",
        degrade: float = 1.0,
        output_scale: float = 1.0,
        batch_size: int | None = None,
        precision: str = "float32",
    ) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        self.precision = precision
        paths = [weights] if isinstance(weights, (str, Path)) else list(weights)
        if not paths:
            raise ValueError("LearnedSimulator needs at least one generator checkpoint")
        if histogram not in HISTOGRAM_MODES:
            raise ValueError(f"histogram must be one of {HISTOGRAM_MODES}, got {histogram!r}")
        self.device = torch.device(device)
        self.nets, self.hists, self.meta = [], [], []
        for p in paths:
            gen, hist, meta = load_generator(p, self.device)
            self.nets.append(gen)
            self.hists.append(hist)
            self.meta.append(meta)
        self.change_interval = max(1, int(change_interval))
        self.histogram = histogram
        self.degrade = float(degrade)
        self.output_scale = float(output_scale)
        if batch_size is None:
            batch_size = 16 if self.device.type == "cpu" else 256
        self.batch_size = int(batch_size)
        self._rng = torch.Generator().manual_seed(seed)
        self._calls = 0
        self.net_index = 0
        self._frozen_luts: dict[int, torch.Tensor] = {}
        self._fov_checked: set = set()

    def fit_source(self, ct_hu: torch.Tensor) -> None:
        """Fix every net's histogram LUT from a sample of input CT (HU, any shape): the source
        distribution the "first_batch" mode maps onto the training CT."""
        ct = torch.as_tensor(ct_hu).to(self.device)
        for i, hist in enumerate(self.hists):
            self._frozen_luts[i] = hist.lut(window_ct(ct, hist.window).reshape(1, -1))

    @property
    def num_nets(self) -> int:
        return len(self.nets)

    def _pick(self) -> int:
        if self._calls % self.change_interval == 0 and self.num_nets > 1:
            self.net_index = int(torch.randint(self.num_nets, (1,), generator=self._rng))
        self._calls += 1
        return self.net_index

    def _check_field_of_view(self, i: int, probe) -> None:
        meta = self.meta[i]
        if probe is None or "image_size" not in meta or "pixel_spacing_m" not in meta:
            return
        key = (i, probe.depth_px, probe.width_px, probe.depth_spacing, probe.width_spacing)
        if key in self._fov_checked:
            return
        self._fov_checked.add(key)
        net = [s * d for s, d in zip(meta["image_size"], meta["pixel_spacing_m"], strict=True)]
        img = [probe.depth_px * probe.depth_spacing, probe.width_px * probe.width_spacing]
        if any(abs(a / b - 1) > 0.1 for a, b in zip(img, net, strict=True)):
            warnings.warn(
                f"learned net {i} was trained on a {net[0] * 1e3:.0f} x {net[1] * 1e3:.0f} mm "
                f"field of view, the probe images {img[0] * 1e3:.0f} x {img[1] * 1e3:.0f} mm: "
                "its images are stretched; train a net on pairs of the probe's geometry",
                stacklevel=3,
            )

    @torch.no_grad()  # not inference_mode: envs update observations in place at autoresets
    def simulate(self, slices: Slices, nets: torch.Tensor | None = None) -> torch.Tensor:
        """(N, E, H, W) images in [0, 1]. ``nets`` (N,) int: the net (index into the loaded
        ones) of each env; None: one net for the batch, redrawn every ``change_interval``
        calls."""
        n = slices.ct.shape[0]
        if nets is None:
            return self._simulate_net(slices.ct, self._pick(), slices.probe)
        nets = torch.as_tensor(nets, dtype=torch.long).reshape(-1).cpu()
        if nets.shape[0] != n:
            raise ValueError(f"nets has {nets.shape[0]} entries for {n} slices")
        if n and (int(nets.min()) < 0 or int(nets.max()) >= self.num_nets):
            raise ValueError(f"net indices must be in [0, {self.num_nets}), got {nets.tolist()}")
        out = torch.empty(slices.ct.shape, dtype=torch.float32, device=slices.ct.device)
        for i in nets.unique().tolist():
            rows = torch.nonzero(nets == i).flatten().to(slices.ct.device)
            out[rows] = self._simulate_net(slices.ct[rows], i, slices.probe)
        return out

    def _simulate_net(self, ct: torch.Tensor, i: int, probe=None) -> torch.Tensor:
        n, e, h, w = ct.shape
        self._check_field_of_view(i, probe)
        gen, hist, meta = self.nets[i], self.hists[i], self.meta[i]
        size = tuple(meta.get("input_size") or (h, w))
        x = ct.reshape(n * e, 1, h, w).to(self.device)
        outs = []
        for k in range(0, x.shape[0], self.batch_size):
            xb = window_ct(x[k : k + self.batch_size], hist.window)
            if tuple(xb.shape[-2:]) != size:
                xb = F.interpolate(xb, size=size, mode="bilinear", align_corners=False)
            if self.degrade > 1:
                xb = down_up(xb, self.degrade)
            if self.histogram == "per_image":
                xb = hist.match(xb, per_image=True)
            elif self.histogram == "first_batch":
                if i not in self._frozen_luts:
                    self._frozen_luts[i] = hist.lut(xb)
                xb = hist.apply(xb, self._frozen_luts[i])
            with torch.autocast(
                self.device.type, torch.bfloat16, enabled=self.precision == "bfloat16"
            ):
                y = gen(xb).float()
            if tuple(y.shape[-2:]) != (h, w):
                y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
            outs.append(y)
        img = (torch.cat(outs) * self.output_scale).clamp_(0, 1)
        return img.reshape(n, e, h, w).to(device=ct.device, dtype=torch.float32)
