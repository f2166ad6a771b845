"""The learned-simulator generator checkpoint: what ``sonogym lb-train`` writes and the
simulator loads (network config and weights, histogram reference, input size, CT window).

Loading never unpickles code: ``torch.load(weights_only=True)`` accepts only tensors and plain
containers, and the format tag is checked before anything is built.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from sonogym.ultrasound.learned.histogram import HistogramReference
from sonogym.ultrasound.learned.networks import UNet, UNetConfig

CHECKPOINT_FORMAT = "sonogym-lb-generator"
CHECKPOINT_VERSION = 1


def save_generator(path: str | Path, gen: UNet, hist: HistogramReference, **meta) -> Path:
    """Write a generator checkpoint atomically (temporary file, then rename); ``meta``: plain
    values (numbers, strings, lists) stored beside the weights."""
    return save_checkpoint(
        path,
        {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "config": gen.config.to_dict(),
            "state_dict": gen.state_dict(),
            "histogram": hist.state_dict(),
            **meta,
        },
    )


def save_checkpoint(path: str | Path, ck: dict) -> Path:
    """``torch.save`` of a checkpoint dict to a temporary file renamed over ``path``."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    torch.save(ck, tmp)
    os.replace(tmp, path)
    return path


def read_checkpoint(path: str | Path, device: torch.device | str = "cpu") -> dict:
    """The checkpoint dict of ``path`` (tensors and plain values only), format checked."""
    path = Path(path)
    try:
        ck = torch.load(path, map_location=device, weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:  # not a torch file, truncated, or holds pickled objects
        raise ValueError(
            f"{path}: not a readable sonogym learned-simulator generator checkpoint ({e}); "
            "give a generator.pt written by sonogym lb-train"
        ) from None
    if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a sonogym learned-simulator generator checkpoint")
    return ck


def load_generator(
    path: str | Path, device: torch.device | str = "cpu"
) -> tuple[UNet, HistogramReference, dict]:
    """(generator in eval mode, histogram reference, the checkpoint's other fields)."""
    ck = read_checkpoint(path, device)
    gen = UNet(UNetConfig.from_dict(ck["config"])).to(device)
    gen.load_state_dict(ck["state_dict"])
    gen.eval()
    hist = HistogramReference.from_state_dict(ck["histogram"])
    meta = {k: v for k, v in ck.items() if k not in ("config", "state_dict", "histogram")}
    return gen, hist, meta
