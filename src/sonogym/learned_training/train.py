"""pix2pix training of the CT -> ultrasound generator (``sonogym lb-train``).

Adam (lr 2e-4, betas 0.5/0.999) on the generator (:class:`UNet`) and a PatchGAN discriminator
(base width 32 by default, half pix2pix's 64: the 64-wide one costs ~3x the generator on CPU);
generator loss = L1 x ``l1_weight`` (1) + non-saturating GAN x ``gan_weight`` (0.01), the
paper's weights; discriminator: BCE on real and fake pairs, halved. Inputs are windowed CT in
[0, 1], randomly down/up-sampled (augmentation) and histogram matched (one LUT per batch) to
the training CT, exactly as the simulator prepares slices. Losses go to TensorBoard
(``out/tb``); held-out SSIM / PSNR / L1 (torchmetrics) to ``out/metrics.json``. LPIPS is not
computed: it needs pretrained weights that cannot be downloaded offline.

``out/generator.pt`` holds everything the simulator needs: the network config and weights, the
histogram reference, the input size and the CT window.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from sonogym.learned_training.data import PairedDataset, read_manifest
from sonogym.progress import progress_bar
from sonogym.ultrasound.learned.augment import random_down_up
from sonogym.ultrasound.learned.checkpoint import save_generator
from sonogym.ultrasound.learned.histogram import HistogramReference
from sonogym.ultrasound.learned.networks import PatchDiscriminator, UNet, UNetConfig


def fit_size(h: int, w: int, factor: int) -> tuple[int, int]:
    """(h, w) rounded up to multiples of ``factor`` (the U-Net's total stride)."""
    return (-(-h // factor) * factor, -(-w // factor) * factor)


def _resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False)


@torch.no_grad()
def evaluate(
    gen: UNet, hist: HistogramReference, ds: PairedDataset, size, batch_size: int = 16
) -> dict:
    """Held-out SSIM, PSNR (data range 1) and L1 of the generator on a dataset."""
    from torchmetrics.functional.image import (
        peak_signal_noise_ratio,
        structural_similarity_index_measure,
    )

    if len(ds) == 0:
        return {"ssim": None, "psnr": None, "l1": None, "n": 0}
    dev = next(gen.parameters()).device
    was_training = gen.training
    gen.eval()
    preds = []
    for i in range(0, len(ds), batch_size):
        ct = ds.ct[i : i + batch_size].to(dev)
        x = hist.match(_resize(ct, size))
        preds.append(_resize(gen(x), tuple(ct.shape[-2:])).cpu())
    gen.train(was_training)
    pred, target = torch.cat(preds), ds.us
    return {
        "ssim": float(structural_similarity_index_measure(pred, target, data_range=1.0)),
        "psnr": float(peak_signal_noise_ratio(pred, target, data_range=1.0)),
        "l1": float((pred - target).abs().mean()),
        "n": len(ds),
    }


def _gan_step(gen, disc, opt_g, opt_d, bce, x, us, l1_weight: float, gan_weight: float):
    """One pix2pix update: the discriminator on (x, us) against (x, G(x)), then the generator
    on L1 + GAN; returns the losses ({"l1", "gan", "d"}) and the generator's total loss."""
    fake = gen(x)
    opt_d.zero_grad(set_to_none=True)
    d_real, d_fake = disc(x, us), disc(x, fake.detach())
    loss_d = 0.5 * (bce(d_real, torch.ones_like(d_real)) + bce(d_fake, torch.zeros_like(d_fake)))
    loss_d.backward()
    opt_d.step()
    opt_g.zero_grad(set_to_none=True)
    d_fake = disc(x, fake)
    loss_gan = bce(d_fake, torch.ones_like(d_fake))
    loss_l1 = (fake - us).abs().mean()
    loss_g = l1_weight * loss_l1 + gan_weight * loss_gan
    loss_g.backward()
    opt_g.step()
    return {"l1": loss_l1.item(), "gan": loss_gan.item(), "d": loss_d.item()}, loss_g


def _metrics(seed, steps, wall_s, history, final, evals, config) -> dict:
    """``metrics.json``: the final held-out figures, the mean training L1 over the first and
    the last tenth of the steps, and the settings."""
    k = max(1, len(history) // 10)
    return {
        "seed": seed,
        "steps": steps,
        "wall_s": round(wall_s, 2),
        "train_l1_first": sum(r["l1"] for r in history[:k]) / k,
        "train_l1_last": sum(r["l1"] for r in history[-k:]) / k,
        "test": final,
        "test_history": evals,
        "lpips": None,
        "lpips_note": "LPIPS not computed: its pretrained weights cannot be downloaded offline",
        "config": config,
    }


def train_pix2pix(
    data_dir: str | Path,
    out: str | Path,
    seed: int = 0,
    steps: int = 2000,
    width: int = 16,
    depth: int = 4,
    batch_size: int = 8,
    lr: float = 2e-4,
    l1_weight: float = 1.0,
    gan_weight: float = 0.01,
    disc_width: int = 32,
    disc_layers: int = 3,
    eval_every: int = 500,
    log_every: int = 10,
    device: torch.device | str = "cpu",
    progress: bool = True,
    tensorboard: bool = True,
) -> dict:
    """Train one generator; returns the metrics also written to ``out/metrics.json``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(device)
    torch.manual_seed(seed)
    g = torch.Generator(device="cpu").manual_seed(seed)
    manifest = read_manifest(data_dir)
    train, test = PairedDataset(data_dir, "train"), PairedDataset(data_dir, "test")
    if len(train) == 0:
        raise ValueError(f"{data_dir}: no training pairs")
    window = train.window
    hist = HistogramReference.fit_windowed(train.ct, window=window)
    gen = UNet(UNetConfig.from_width(width, depth)).to(device)
    disc = PatchDiscriminator(2, disc_width, disc_layers).to(device)
    size = fit_size(*train.ct.shape[-2:], gen.factor)
    opt_g = torch.optim.Adam(gen.parameters(), lr=lr, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(disc.parameters(), lr=lr, betas=(0.5, 0.999))
    bce = torch.nn.BCEWithLogitsLoss()
    writer = None
    if tensorboard:
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / "tb"))
    history: list[dict] = []
    evals: list[dict] = []
    t0 = time.time()
    bar = progress_bar(steps, f"lb-train seed {seed}", unit="step", enabled=progress)
    for step in range(steps):
        idx = torch.randint(len(train), (min(batch_size, len(train)),), generator=g)
        ct = _resize(train.ct[idx], size).to(device)
        us = _resize(train.us[idx], size).to(device)
        x = hist.match(random_down_up(ct, g))
        rec, loss_g = _gan_step(gen, disc, opt_g, opt_d, bce, x, us, l1_weight, gan_weight)
        rec = {"step": step, **rec}
        history.append(rec)
        if step % log_every == 0 or step == steps - 1:
            bar.set_postfix(l1=f"{rec['l1']:.4f}", d=f"{rec['d']:.3f}")
            if writer is not None:
                writer.add_scalar("loss/l1", rec["l1"], step)
                writer.add_scalar("loss/gan_g", rec["gan"], step)
                writer.add_scalar("loss/d", rec["d"], step)
                writer.add_scalar("loss/g_total", loss_g.item(), step)
        if eval_every and (step + 1) % eval_every == 0 and step != steps - 1:
            m = {"step": step + 1, **evaluate(gen, hist, test, size)}
            evals.append(m)
            if writer is not None and m["n"]:
                for k in ("ssim", "psnr", "l1"):
                    writer.add_scalar(f"test/{k}", m[k], step + 1)
        bar.update(1)
    bar.close()
    final = {"step": steps, **evaluate(gen, hist, test, size)}
    evals.append(final)
    if writer is not None:
        if final["n"]:
            for k in ("ssim", "psnr", "l1"):
                writer.add_scalar(f"test/{k}", final[k], steps)
        writer.close()
    config = {
        "width": width, "depth": depth, "batch_size": batch_size, "lr": lr,
        "l1_weight": l1_weight, "gan_weight": gan_weight, "disc_width": disc_width,
        "disc_layers": disc_layers, "input_size": list(size),
    }  # fmt: skip
    metrics = _metrics(seed, steps, time.time() - t0, history, final, evals, config)
    save_generator(
        out / "generator.pt",
        gen.cpu(),
        hist,
        input_size=list(size),
        image_size=list(train.ct.shape[-2:]),
        ct_window_hu=list(window),
        pixel_spacing_m=manifest["pixel_spacing_m"],
        seed=seed,
        steps=steps,
        data=str(data_dir),
    )
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    with (out / "losses.jsonl").open("w") as f:
        for r in history:
            f.write(json.dumps(r) + "\n")
    return metrics
