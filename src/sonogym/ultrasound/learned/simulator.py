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

With several nets, one net serves the whole batch and a new one is drawn uniformly (seeded
generator) every ``change_interval`` calls (the reference: 100). Not wired into the envs yet.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F

from sonogym.ultrasound.learned.augment import down_up
from sonogym.ultrasound.learned.histogram import window_ct
from sonogym.ultrasound.learned.train import load_generator
from sonogym.ultrasound.slicer import Slices

HISTOGRAM_MODES = ("per_image", "first_batch", "none")


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
        batch_size: images per forward pass.
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
        batch_size: int = 256,
    ) -> None:
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
        self.batch_size = int(batch_size)
        self._rng = torch.Generator().manual_seed(seed)
        self._calls = 0
        self.net_index = 0
        self._frozen_luts: dict[int, torch.Tensor] = {}

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

    @torch.inference_mode()
    def simulate(self, slices: Slices) -> torch.Tensor:
        ct = slices.ct
        n, e, h, w = ct.shape
        i = self._pick()
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
            y = gen(xb)
            if tuple(y.shape[-2:]) != (h, w):
                y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
            outs.append(y)
        img = (torch.cat(outs) * self.output_scale).clamp_(0, 1)
        return img.reshape(n, e, h, w).to(device=ct.device, dtype=torch.float32)
