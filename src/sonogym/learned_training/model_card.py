"""Held-out evaluation of learned simulators: bone-surface F1, the linear CT -> US baseline,
pairwise similarity of nets, and the model card's numbers.

**Bone-surface F1** (per image column = one beam of the linear array):

* true surface: the first row, from the probe face, whose label is a bone id
  (``sonogym.anatomy.labels.BONE_IDS``); none if the beam meets no bone;
* detected surface in an image: the row r maximising the "bright over shadow" contrast
  ``I[r] - mean(I[r+1 : r+1+shadow_px])`` (a bone surface is a bright echo with an acoustic
  shadow below), if that contrast is at least ``threshold``; none otherwise. Rows within
  ``shadow_px`` of the bottom use the rows that remain;
* a detection is a true positive if its beam has a true surface within ``tol_px`` rows;
  precision = TP / detections, recall = TP / beams with a true surface, F1 = their harmonic
  mean, counted over all beams of all images of a set (0 when undefined).

Defaults on the recipe's 1 mm pixels: ``threshold`` 0.2, ``shadow_px`` 10 (1 cm), ``tol_px`` 3
(3 mm). The ``physical`` target images themselves score well below 1 (the posterior surfaces of
oblique laminae reflect weakly), so the card also reports the target's F1 as a ceiling.

**Linear baseline**: us ~ a * ct + b, ct windowed to [0, 1] with the data's window, a and b by
least squares over every pixel of the training split.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from sonogym.anatomy.labels import BONE_IDS


def bone_surface_rows(labels: torch.Tensor) -> torch.Tensor:
    """(..., H, W) label ids -> (..., W) int64 row of the first bone pixel per column, -1 if
    the column has no bone."""
    lab = torch.as_tensor(labels).long()
    ids = torch.tensor(sorted(BONE_IDS), dtype=torch.long, device=lab.device)
    bone = torch.isin(lab, ids)
    h = bone.shape[-2]
    rows = torch.arange(h, device=lab.device).view(h, 1)
    first = torch.where(bone, rows, torch.full_like(rows, h)).amin(-2)
    return torch.where(first < h, first, torch.full_like(first, -1))


def detect_surface_rows(
    images: torch.Tensor,
    threshold: float = 0.2,
    shadow_px: int = 10,
    shadow_max: float = 0.1,
    skip_px: int = 5,
) -> torch.Tensor:
    """(..., H, W) intensities -> (..., W) int64 row of the strongest bright-over-shadow edge
    per column (rows below ``skip_px``, mean of the ``shadow_px`` rows below at most
    ``shadow_max``), -1 where its contrast is below ``threshold``."""
    x = torch.as_tensor(images).float()
    h = x.shape[-2]
    csum = torch.cat([torch.zeros_like(x[..., :1, :]), x.cumsum(-2)], -2)  # (..., H+1, W)
    r = torch.arange(h, device=x.device)
    lo = (r + 1).clamp(max=h)
    hi = (r + 1 + shadow_px).clamp(max=h)
    n = (hi - lo).clamp(min=1).to(x.dtype).view(h, 1)
    below = (csum[..., hi, :] - csum[..., lo, :]) / n
    below = torch.where((hi > lo).view(h, 1), below, torch.zeros_like(below))
    ok = (below <= shadow_max) & (r >= skip_px).view(h, 1) & (hi > lo).view(h, 1)
    contrast = torch.where(ok, x - below, torch.full_like(x, -1.0))
    best, row = contrast.max(-2)
    return torch.where(best >= threshold, row, torch.full_like(row, -1))


def surface_f1(pred_rows: torch.Tensor, true_rows: torch.Tensor, tol_px: int = 3) -> dict:
    """Precision, recall and F1 of detected surface rows against true ones (both (..., W),
    -1 = none), counted over all columns; see the module docstring."""
    p, t = torch.as_tensor(pred_rows), torch.as_tensor(true_rows)
    det, has = p >= 0, t >= 0
    tp = int((det & has & ((p - t).abs() <= tol_px)).sum())
    nd, nt = int(det.sum()), int(has.sum())
    prec = tp / nd if nd else 0.0
    rec = tp / nt if nt else 0.0
    f1 = 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0
    return {"precision": prec, "recall": rec, "f1": f1, "tp": tp, "detected": nd, "true": nt}


def bone_surface_f1(
    images: torch.Tensor,
    labels: torch.Tensor,
    threshold: float = 0.2,
    shadow_px: int = 10,
    tol_px: int = 3,
) -> dict:
    """Bone-surface F1 of images (..., H, W) against their label slices."""
    return surface_f1(
        detect_surface_rows(images, threshold, shadow_px), bone_surface_rows(labels), tol_px
    )


# ---------------------------------------------------------------- metrics and baseline
def image_metrics(pred: torch.Tensor, target: torch.Tensor) -> dict:
    """SSIM, PSNR (data range 1) and L1 of (N, 1, H, W) images in [0, 1] (torchmetrics)."""
    from torchmetrics.functional.image import (
        peak_signal_noise_ratio,
        structural_similarity_index_measure,
    )

    return {
        "ssim": float(structural_similarity_index_measure(pred, target, data_range=1.0)),
        "psnr": float(peak_signal_noise_ratio(pred, target, data_range=1.0)),
        "l1": float((pred - target).abs().mean()),
    }


class LinearBaseline:
    """us ~ a * ct + b on windowed CT in [0, 1], fitted by least squares."""

    def __init__(self, a: float = 0.0, b: float = 0.0) -> None:
        self.a, self.b = float(a), float(b)

    @classmethod
    def fit(cls, ct: torch.Tensor, us: torch.Tensor) -> LinearBaseline:
        x = ct.reshape(-1).double()
        y = us.reshape(-1).double()
        design = torch.stack([x, torch.ones_like(x)], 1)
        sol = torch.linalg.lstsq(design, y.unsqueeze(1)).solution.flatten()
        return cls(float(sol[0]), float(sol[1]))

    def __call__(self, ct: torch.Tensor) -> torch.Tensor:
        return (self.a * ct + self.b).clamp(0, 1)


@torch.no_grad()
def predict(gen, hist, ct: torch.Tensor, size, batch_size: int = 16) -> torch.Tensor:
    """Generator output for windowed CT (N, 1, H, W), as in training (one LUT per batch)."""
    from sonogym.learned_training.train import _resize

    outs = []
    for i in range(0, ct.shape[0], batch_size):
        x = hist.match(_resize(ct[i : i + batch_size], size))
        outs.append(_resize(gen(x), tuple(ct.shape[-2:])))
    return torch.cat(outs).clamp(0, 1)


def _labels(root: Path, split: str) -> torch.Tensor:
    from sonogym.learned_training.data import load_labels, read_manifest

    m = read_manifest(root)
    labs = [load_labels(root, e) for e in m["pairs"] if e["split"] == split]
    if any(lab is None for lab in labs):
        raise ValueError(f"{root}: some {split} pairs have no label slice (key 'labels')")
    return torch.from_numpy(np.stack(labs))[:, None]


def evaluate_set(pred: torch.Tensor, us: torch.Tensor, labels: torch.Tensor) -> dict:
    return {**image_metrics(pred, us), "bone_f1": bone_surface_f1(pred, labels)["f1"]}


def model_card(work: str | Path) -> dict:
    """Per-net held-out metrics (own split and unseen phantom), the linear baseline's, the
    target images' bone F1, training cost and the pairwise SSIM matrix of the nets on one common
    input (net 0's unseen-phantom CT). Returns {"json": ..., "markdown": ...}."""
    from sonogym.learned_training import recipe
    from sonogym.learned_training.data import PairedDataset
    from sonogym.ultrasound.learned.checkpoint import load_generator

    work = Path(work)
    nets, rows = [], []
    for k in range(recipe.NUM_NETS):
        main, unseen = recipe.data_dirs(work, k)
        gen, hist, meta = load_generator(recipe.run_dir(work, k) / "generator.pt")
        size = tuple(meta["input_size"])
        train = PairedDataset(main, "train")
        base = LinearBaseline.fit(train.ct, train.us)
        tm = json.loads((recipe.run_dir(work, k) / "metrics.json").read_text())
        entry = {"net": k, "seed": k, "steps": tm["steps"], "train_wall_s": tm["wall_s"],
                 "train_l1_first": tm["train_l1_first"], "train_l1_last": tm["train_l1_last"],
                 "baseline": {"a": base.a, "b": base.b},
                 "physics": train.manifest["source"].get("model")}  # fmt: skip
        for name, root in (("test", main), ("unseen", unseen)):
            ds = PairedDataset(root, "test")
            labels = _labels(root, "test")
            entry[name] = {
                "n": len(ds),
                "net": evaluate_set(predict(gen, hist, ds.ct, size), ds.us, labels),
                "linear": evaluate_set(base(ds.ct), ds.us, labels),
                "target_bone_f1": bone_surface_f1(ds.us, labels)["f1"],
            }
        nets.append(entry)
        rows.append((gen, hist, size))
    common = PairedDataset(recipe.data_dirs(work, 0)[1], "test").ct
    outs = [predict(g, h, common, s) for g, h, s in rows]
    from torchmetrics.functional.image import structural_similarity_index_measure as ssim

    pair = [[float(ssim(a, b, data_range=1.0)) for b in outs] for a in outs]
    from sonogym.ultrasound.learned.shipped import net_digests

    # the shipped files' (``recipe.ship`` rewrites each generator's metadata): what runs record
    digests = net_digests(tuple(range(recipe.NUM_NETS)))
    card = {"nets": nets, "digests": digests, "pairwise_ssim": pair,
            "common_input": "net 0 unseen-phantom CT",
            "recipe": {"image_size": recipe.IMAGE_SIZE, "pixel_spacing_m": recipe.PIXEL_SPACING,
                       "train_phantoms": recipe.TRAIN_PHANTOMS,
                       "unseen_phantom": recipe.UNSEEN_PHANTOM,
                       "pairs_per_net": recipe.PAIRS_PER_NET, "train": recipe.TRAIN}}  # fmt: skip
    return {"json": card, "markdown": _markdown(card)}


def _markdown(card: dict) -> str:
    lines = ["| net | gain dB | frequency MHz | pulse cycles | f-number | tissue alpha x "
             "| TGC dB/cm/MHz |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    for e in card["nets"]:
        m = e.get("physics")
        if m:
            lines.append(
                f"| {e['net']} | {m['gain_db']:+.1f} | {m['frequency_hz'] / 1e6:.2f} "
                f"| {m['pulse_cycles']:.2f} | {m['f_number']:.2f} "
                f"| {m['tissue_alpha_scale']:.2f} | {m['tgc_alpha_db_cm_mhz']:.2f} |"
            )
    lines += [
        "",
        "| net | split | n | SSIM net / linear | PSNR dB net / linear | L1 net / linear "
        "| bone F1 net / linear / target |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in card["nets"]:
        for split in ("test", "unseen"):
            s = e[split]
            n, lin = s["net"], s["linear"]
            lines.append(
                f"| {e['net']} | {split} | {s['n']} | {n['ssim']:.3f} / {lin['ssim']:.3f} "
                f"| {n['psnr']:.2f} / {lin['psnr']:.2f} | {n['l1']:.3f} / {lin['l1']:.3f} "
                f"| {n['bone_f1']:.3f} / {lin['bone_f1']:.3f} / {s['target_bone_f1']:.3f} |"
            )
    lines += ["", "| net | steps | train time s | train L1 first -> last | baseline a, b |",
              "|---|---|---|---|---|"]  # fmt: skip
    for e in card["nets"]:
        lines.append(
            f"| {e['net']} | {e['steps']} | {e['train_wall_s']:.0f} "
            f"| {e['train_l1_first']:.3f} -> {e['train_l1_last']:.3f} "
            f"| {e['baseline']['a']:.3f}, {e['baseline']['b']:.3f} |"
        )
    k = len(card["pairwise_ssim"])
    lines += ["", "Pairwise SSIM (" + card["common_input"] + "):", "",
              "| | " + " | ".join(f"net {j}" for j in range(k)) + " |",
              "|---" * (k + 1) + "|"]  # fmt: skip
    for i, row in enumerate(card["pairwise_ssim"]):
        lines.append(f"| net {i} | " + " | ".join(f"{v:.3f}" for v in row) + " |")
    return "\n".join(lines) + "\n"
