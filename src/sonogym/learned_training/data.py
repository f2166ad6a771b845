"""Paired CT / ultrasound slices on disk, the reader, and the default (simulated) pairs.

Format (version 1): a folder with ``manifest.json``::

    {"format": "sonogym-paired-ct-us", "version": 1,
     "pixel_spacing_m": [depth, width], "ct_window_hu": [-300.0, 1641.0],
     "image_size": [H, W], "source": {...free-form provenance, e.g. "us_model"...},
     "pairs": [{"ct": "pairs/00000.npz", "us": "pairs/00000.npz", "split": "train"}, ...]}

and ``pairs/NNNNN.npz`` files holding ``ct`` (float32 (H, W), Hounsfield units) and ``us``
(float32 (H, W) in [0, 1]); rows run along depth (the beam), columns along the array. ``ct``
and ``us`` may name different files (``.npz`` with key ``ct`` / ``us``, or ``.npy``), so real
paired CT-US data converted to arrays drops in unchanged. ``split`` is ``train`` or ``test``
(held out, for SSIM / PSNR).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from sonogym.progress import progress_bar
from sonogym.ultrasound.learned.histogram import CT_WINDOW_HU, window_ct

FORMAT = "sonogym-paired-ct-us"
VERSION = 1
SPLITS = ("train", "test")
#: Phantom seeds for training pairs start here, apart from the env seeds (0, 1, 2, ...).
DEFAULT_SEED_BASE = 1000


class PairedDataError(ValueError):
    """A paired-data folder is missing, malformed, or inconsistent."""


def read_manifest(root: str | Path) -> dict:
    root = Path(root)
    path = root / "manifest.json"
    if not path.is_file():
        raise PairedDataError(f"no manifest.json in {root} (see docs/learned.md for the format)")
    try:
        m = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise PairedDataError(f"{path}: not valid JSON ({e})") from e
    for key in ("version", "pixel_spacing_m", "ct_window_hu", "pairs"):
        if key not in m:
            raise PairedDataError(f"{path}: missing key {key!r}")
    if m["version"] != VERSION:
        raise PairedDataError(f"{path}: version {m['version']} is not supported (want {VERSION})")
    for i, p in enumerate(m["pairs"]):
        if not {"ct", "us", "split"} <= set(p):
            raise PairedDataError(f"{path}: pair {i} needs 'ct', 'us' and 'split'")
        if p["split"] not in SPLITS:
            raise PairedDataError(f"{path}: pair {i} split {p['split']!r} not in {SPLITS}")
    source = m.get("source")
    if isinstance(source, dict) and "preset" in source and "us_model" not in source:
        source["us_model"] = source.pop("preset")  # the key's name in older manifests
    return m


def _load_array(root: Path, rel: str, key: str) -> np.ndarray:
    path = root / rel
    if not path.is_file():
        raise PairedDataError(f"missing pair file {path}")
    if path.suffix == ".npy":
        return np.load(path)
    with np.load(path) as z:
        if key not in z:
            raise PairedDataError(f"{path}: no array {key!r} (has {list(z.keys())})")
        return z[key]


def load_pair(root: str | Path, entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """(ct HU, us [0, 1]) float32 (H, W) arrays of one manifest entry."""
    root = Path(root)
    ct = np.asarray(_load_array(root, entry["ct"], "ct"), dtype=np.float32)
    us = np.asarray(_load_array(root, entry["us"], "us"), dtype=np.float32)
    if ct.ndim != 2 or ct.shape != us.shape:
        raise PairedDataError(
            f"pair {entry['ct']}: CT {ct.shape} and US {us.shape} must be equal 2-D shapes"
        )
    return ct, us


class PairedDataset(Dataset):
    """Pairs of one split as tensors: (ct, us), each (1, H, W) float32.

    ``ct`` is windowed to [0, 1] with the manifest's HU window (the paper's range by default);
    ``us`` is in [0, 1]. Everything is loaded on construction (the default sets are small).
    """

    def __init__(self, root: str | Path, split: str = "train") -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        self.root = Path(root)
        self.manifest = read_manifest(self.root)
        self.window = tuple(float(v) for v in self.manifest["ct_window_hu"])
        entries = [p for p in self.manifest["pairs"] if p["split"] == split]
        cts, uss = [], []
        for e in entries:
            ct, us = load_pair(self.root, e)
            if cts and ct.shape != cts[0].shape:
                raise PairedDataError(
                    f"pair {e['ct']}: shape {ct.shape} differs from the first pair's "
                    f"{cts[0].shape}; resample the pairs to one size"
                )
            cts.append(ct)
            uss.append(us)
        if cts:
            ct_hu = torch.from_numpy(np.stack(cts))[:, None]
            self.ct = window_ct(ct_hu, self.window)
            self.us = torch.from_numpy(np.stack(uss))[:, None].clamp(0, 1)
        else:
            self.ct = self.us = torch.zeros(0, 1, 1, 1)

    def __len__(self) -> int:
        return self.ct.shape[0]

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.ct[i], self.us[i]


def write_manifest(root: Path, pairs: list[dict], spacing, size, window, source: dict) -> Path:
    m = {
        "format": FORMAT,
        "version": VERSION,
        "pixel_spacing_m": [float(s) for s in spacing],
        "ct_window_hu": [float(w) for w in window],
        "image_size": [int(s) for s in size],
        "source": source,
        "pairs": pairs,
    }
    path = Path(root) / "manifest.json"
    path.write_text(json.dumps(m, indent=1))
    return path


def random_physical_model(rng: np.random.Generator):
    """The ``physical`` model with randomised gain, PSF (frequency, pulse length, f-number)
    and attenuation (tissue alpha scale and the TGC's compensated alpha)."""
    from sonogym.ultrasound.simulator import PhysicalModel
    from sonogym.ultrasound.tissues import TissueTable, physical_table

    base = physical_table()
    scale = float(rng.uniform(0.7, 1.4))
    tissues = {k: dataclasses.replace(t, alpha=t.alpha * scale) for k, t in base.tissues.items()}
    table = TissueTable(base.label_tissue, tissues, base.default, name="physical")
    return PhysicalModel(
        gain=float(rng.uniform(-6.0, 6.0)),
        frequency=float(rng.uniform(3.0, 6.0)) * 1e6,
        pulse_cycles=float(rng.uniform(2.0, 4.0)),
        f_number=float(rng.uniform(3.0, 5.0)),
        tgc_alpha=float(rng.uniform(0.45, 0.75)),
        tissues=table,
    )


def _model_summary(model) -> dict:
    return {
        "gain_db": model.gain,
        "frequency_hz": model.frequency,
        "pulse_cycles": model.pulse_cycles,
        "f_number": model.f_number,
        "tgc_alpha_db_cm_mhz": model.tgc_alpha,
        "tissue_alpha_scale": _alpha_scale(model),
    }


def _alpha_scale(model) -> float | None:
    from sonogym.ultrasound.tissues import physical_table

    base = physical_table()
    for k, t in model.tissues.tissues.items():
        if base.tissues[k].alpha > 0:
            return float(t.alpha / base.tissues[k].alpha)
    return None


def load_labels(root: str | Path, entry: dict) -> np.ndarray | None:
    """The label slice (uint8 (H, W)) stored with a pair's US file under key ``labels``, or
    None when the pair has none (real data usually has none)."""
    path = Path(root) / entry["us"]
    if path.suffix != ".npz" or not path.is_file():
        return None
    with np.load(path) as z:
        return np.asarray(z["labels"], dtype=np.uint8) if "labels" in z else None


def write_default_pairs(
    out: str | Path,
    n: int = 2000,
    seeds: Sequence[int] = tuple(range(DEFAULT_SEED_BASE, DEFAULT_SEED_BASE + 5)),
    image_size: tuple[int, int] = (192, 160),
    pixel_spacing: float = 0.5e-3,
    phantom_spacing: float = 1e-3,
    test_fraction: float = 0.125,
    rng_seed: int = 0,
    models_per_seed: int = 8,
    progress: bool = False,
    model_seed: int | None = None,
) -> Path:
    """Simulated training pairs: CT slices and ``physical``-model images of phantoms.

    Phantom ``seeds`` should stay apart from the env seeds (default 1000-1004). Probe poses are
    random on the back's skin around the spine (x within +-40 mm, z along the lumbar spine,
    any yaw, tilt within +-0.25 rad). The slicer samples every pixel (``upsample=False``, finer
    than the envs' block sampling); each group of pairs gets its own randomised model
    (:func:`random_physical_model`). With ``model_seed`` every pair uses one model drawn from
    that seed instead (a per-net imaging "style", see ``shipped.py``). CT is stored clamped to
    the paper's window; the label slice is stored too (key ``labels``, uint8, for the bone
    surface F1). Returns the manifest path. The held-out split is the last ``test_fraction`` of
    each phantom's pairs.
    """
    from sonogym.anatomy.phantom import PhantomParams, load_phantom
    from sonogym.anatomy.surface import SkinSurface
    from sonogym.ultrasound.probe import ProbeGeometry
    from sonogym.ultrasound.simulator import ModelBasedSimulator
    from sonogym.ultrasound.slicer import Slicer

    out = Path(out)
    (out / "pairs").mkdir(parents=True, exist_ok=True)
    seeds = list(seeds)
    if not seeds or n < 1:
        raise ValueError("need at least one phantom seed and one pair")
    probe = ProbeGeometry.linear_2d(image_size[0], image_size[1], pixel_spacing)
    rng = np.random.default_rng(rng_seed)
    fixed_model = None
    if model_seed is not None:
        fixed_model = random_physical_model(np.random.default_rng(model_seed))
    per_seed = [n // len(seeds) + (i < n % len(seeds)) for i in range(len(seeds))]
    entries: list[dict] = []
    bar = progress_bar(n, "lb-data", unit="pair", enabled=progress)
    for seed, count in zip(seeds, per_seed, strict=True):
        if count == 0:
            continue
        patient = load_phantom(seed, PhantomParams(spacing=phantom_spacing))
        skin = SkinSurface.from_patient(patient)
        slicer = Slicer(patient, probe, upsample=False)
        lo, hi = patient.bounds
        z_lo, z_hi = max(lo[2] + 0.03, -0.10), min(hi[2] - 0.03, 0.12)
        n_test = math.floor(count * test_fraction) if count > 1 else 0
        groups = max(1, min(models_per_seed, count))
        bounds = np.linspace(0, count, groups + 1).astype(int)
        done = 0
        for g0, g1 in zip(bounds[:-1], bounds[1:], strict=True):
            m = g1 - g0
            if m == 0:
                continue
            x = torch.from_numpy(rng.uniform(-0.04, 0.04, m))
            z = torch.from_numpy(rng.uniform(z_lo, z_hi, m))
            yaw = torch.from_numpy(rng.uniform(0, 2 * np.pi, m))
            tilt = torch.from_numpy(rng.uniform(-0.25, 0.25, m))
            pos, rot = skin.surface_pose(x, z, yaw, tilt)
            slices = slicer(pos.double(), rot.double())
            sim = ModelBasedSimulator(fixed_model or random_physical_model(rng))
            us = sim.simulate(slices)[:, 0].numpy().astype(np.float32)
            ct = slices.ct[:, 0].clamp(*CT_WINDOW_HU).numpy().astype(np.float32)
            labels = slices.labels[:, 0].numpy().astype(np.uint8)
            for j in range(m):
                k = len(entries)
                rel = f"pairs/{k:05d}.npz"
                np.savez_compressed(out / rel, ct=ct[j], us=us[j], labels=labels[j])
                split = "test" if done >= count - n_test else "train"
                entries.append({"ct": rel, "us": rel, "split": split, "phantom_seed": int(seed)})
                done += 1
            bar.update(m)
    bar.close()
    source = {
        "generator": "sonogym.learned_training.data.write_default_pairs",
        "us_model": "physical (randomised gain, PSF, attenuation)",
        "phantom_seeds": seeds,
        "phantom_spacing_m": phantom_spacing,
        "slicer_upsample": False,
        "rng_seed": rng_seed,
        "model_seed": model_seed,
        "model": None if fixed_model is None else _model_summary(fixed_model),
    }
    return write_manifest(
        out, entries, (pixel_spacing, pixel_spacing), image_size, CT_WINDOW_HU, source
    )
