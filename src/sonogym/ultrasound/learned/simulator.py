"""``LearnedSimulator``: pix2pix generators behind the ``UltrasoundSimulator`` interface.

Per call, on the N x E slices (in chunks of ``batch_size`` images):
1. window the CT (HU) to [0, 1] with the net's window (the paper's range by default);
2. resize bilinearly to the net's input size (that of its training pairs);
3. optionally degrade by down/up-sampling (``degrade``; the reference uses 4 on 256 x 256);
4. histogram-match to the net's training CT (``histogram``):
   * ``"first_batch"`` (default, the reference's behaviour): one population-level LUT, fitted
     by :meth:`LearnedSimulator.fit_source` on a CT sample (e.g. the patients' volumes or a
     batch of slices) or else from the first chunk the net sees, then reused, so images are
     deterministic and batch independent from then on. Training inputs are matched per batch,
     i.e. at population level too;
   * ``"per_image"``: one LUT per image (batch independent from the first call, but every
     image gets the training histogram, so a slice without bone is stretched until some of it
     reads as bone: use with care);
   * ``"none"``: no matching;
5. run the generator (output in (0, 1), sigmoid), resize back, multiply by ``output_scale``
   (1; the reference's env used 0.1) and clamp to [0, 1].

Which net images which env: ``slices.net_index`` (N,) when set (the envs draw one net per env
at every episode reset, see ``sonogym.envs.imaging``; the envs of one net run as one batch,
whatever their order); else one net serves the whole batch, redrawn uniformly (seeded
generator) every ``change_interval`` calls (the reference: 100). So ``simulate(slices)`` is
the one call of every simulator (``UltrasoundSimulator``).

The generator runs in its inference form (``FastGenerator``: weights prepared once in the
working precision, channels-last; ``sonogym.ultrasound.learned.inference``). ``reference=True``
runs the ``UNet`` modules themselves in float32 instead, one net after the other: the path the
fast one is tested against.

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

from sonogym.ultrasound._workspace import ChunkRunner
from sonogym.ultrasound.learned.augment import down_up
from sonogym.ultrasound.learned.checkpoint import load_generator
from sonogym.ultrasound.learned.histogram import window_ct
from sonogym.ultrasound.learned.inference import PRECISIONS, FastGenerator
from sonogym.ultrasound.slicer import Slices

HISTOGRAM_MODES = ("per_image", "first_batch", "none")
__all__ = ["HISTOGRAM_MODES", "PRECISIONS", "LearnedSimulator"]


class LearnedSimulator:
    """Learning-based ultrasound simulator (``UltrasoundSimulator`` protocol).

    Args:
        weights: one or several ``generator.pt`` files written by ``sonogym lb-train``.
        device: where the nets run; slices on other devices are moved and the images moved
            back.
        seed: seed of the random net choice (slices without ``net_index``).
        change_interval: calls between two random net draws.
        histogram: "per_image", "first_batch" or "none" (see the module docstring).
        degrade: deterministic down/up-sampling factor applied before matching (1 = none).
        output_scale: factor on the generator's output.
        batch_size: images per forward pass (None: 32 on CPU, where chunks of a few MB stay in
            cache, 256 elsewhere). Chunks run on the torch threads side by side
            (``ChunkRunner``, as the model-based simulator's).
        precision: "float32" (default) or "bfloat16": the generator's working precision
            (weights and activations; normalisation statistics stay float32). bfloat16 is
            ~2x faster on CPUs with native bfloat16 (AVX-512 BF16, AMX) and changes images by
            ~5e-4 on average (docs/learned.md); on CPUs without it, it is emulated and slow.
        reference: run the ``UNet`` modules in float32 (the slow reference path the default
            one is tested against) instead of their inference form; needs
            ``precision="float32"``.
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
        reference: bool = False,
    ) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        if reference and precision != "float32":
            raise ValueError(
                "reference=True runs the float32 modules: give precision='float32' with it"
            )
        self.precision = precision
        self.reference = bool(reference)
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
        self._forward = self.nets if reference else [FastGenerator(g, precision) for g in self.nets]
        self.change_interval = max(1, int(change_interval))
        self.histogram = histogram
        self.degrade = float(degrade)
        self.output_scale = float(output_scale)
        if batch_size is None:
            batch_size = 32 if self.device.type == "cpu" else 256
        self.batch_size = int(batch_size)
        self._rng = torch.Generator().manual_seed(seed)
        self._calls = 0
        self.net_index = 0
        self._frozen_luts: dict[int, torch.Tensor] = {}
        self._fov_checked: set = set()
        self._runner = ChunkRunner(self.device)

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
                stacklevel=4,
            )

    @torch.no_grad()  # not inference_mode: envs update observations in place at autoresets
    def simulate(self, slices: Slices) -> torch.Tensor:
        """(N, E, H, W) images in [0, 1]: env i by net ``slices.net_index[i]`` (an index into
        the loaded nets), or, without ``net_index``, all by one net redrawn every
        ``change_interval`` calls."""
        ct = slices.ct
        n, e, h, w = ct.shape
        rows = ct.reshape(n * e, 1, h, w).to(self.device)
        out = torch.empty(rows.shape, dtype=torch.float32, device=self.device)
        if slices.net_index is None:
            groups = [(self._pick(), torch.arange(n * e, device=self.device))]
        else:
            groups = self._groups(slices.net_index, n, e)
        chunks = []
        for i, sel in groups:
            self._check_field_of_view(i, slices.probe)
            for k in range(0, sel.shape[0], self.batch_size):
                chunks.append((i, sel[k : k + self.batch_size]))
        for i, sel in chunks:  # LUTs not fixed yet: from the first chunk of each net, in order
            if self.histogram == "first_batch" and i not in self._frozen_luts:
                x = self._resized(i, rows.index_select(0, sel))
                self._frozen_luts[i] = self.hists[i].lut(x)
        self._runner.run(lambda c, _ws: self._run_chunk(*c, rows, out), chunks)
        return out.view(n, e, h, w).to(ct.device)

    def _groups(self, net_index: torch.Tensor, n: int, e: int):
        """(net, image rows) for every net that images some env: the envs of one net in one
        batch. Reads the group sizes on the host, once per call."""
        nets = torch.as_tensor(net_index).reshape(-1).to(self.device, torch.long)
        if nets.shape[0] != n:
            raise ValueError(f"net_index has {nets.shape[0]} entries for {n} slices")
        counts = torch.bincount(nets.clamp(min=-1) + 1, minlength=self.num_nets + 1).tolist()
        if counts[0] or len(counts) > self.num_nets + 1:
            raise ValueError(f"net indices must be in [0, {self.num_nets}), got {nets.tolist()}")
        order = torch.argsort(nets, stable=True)
        if e > 1:  # env k's images are rows k*e ... k*e + e - 1
            order = (order[:, None] * e + torch.arange(e, device=self.device)).reshape(-1)
        groups, start = [], 0
        for i, c in enumerate(counts[1:]):
            if c:
                groups.append((i, order[start : start + c * e]))
                start += c * e
        return groups

    def _run_chunk(self, i: int, sel: torch.Tensor, rows: torch.Tensor, out: torch.Tensor):
        """Net ``i``'s images of ``rows[sel]`` (HU, (B, 1, H, W)) into the same rows of ``out``."""
        h, w = rows.shape[-2:]
        y = self._forward[i](self._matched(i, self._resized(i, rows.index_select(0, sel))))
        if tuple(y.shape[-2:]) != (h, w):
            y = F.interpolate(y, size=(h, w), mode="bilinear", align_corners=False)
        if self.output_scale != 1:
            y = y.mul_(self.output_scale)
        out.index_copy_(0, sel, y.clamp_(0, 1))

    def _resized(self, i: int, ct: torch.Tensor) -> torch.Tensor:
        """CT rows (HU) windowed, resized to net ``i``'s input and degraded."""
        x = window_ct(ct, self.hists[i].window)
        size = tuple(self.meta[i].get("input_size") or x.shape[-2:])
        if tuple(x.shape[-2:]) != size:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        if self.degrade > 1:
            x = down_up(x, self.degrade)
        return x

    def _matched(self, i: int, x: torch.Tensor) -> torch.Tensor:
        """Net ``i``'s input: ``x`` histogram matched as ``histogram`` says."""
        if self.histogram == "per_image":
            return self.hists[i].match(x, per_image=True)
        if self.histogram == "first_batch":
            return self.hists[i].apply(x, self._frozen_luts[i])
        return x
