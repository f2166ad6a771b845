"""The recipe of the shipped learned-simulator nets: data, training, shipping.

``python -m sonogym.learned_training data|train|ship|card --work DIR`` (``__main__.py``; or
``scripts/train_learned_nets.sh``) rebuilds everything the package ships under
``sonogym/ultrasound/learned/weights/``:

* ``data``: per net k (0-4) a paired set from the ``physical`` ultrasound model on phantoms
  1000-1004 (``train`` / ``test`` split: the last 12.5 % of each phantom's poses) and a set on
  the unseen phantom 1005 (all ``test``), at 100 x 75 px and 1 mm pixels: the field of view of
  the envs' 2-D image (200 x 150 at 0.5 mm) and, within 1 mm, of the surgery volume's slices
  (50 x 37 at 2 mm), at half the 2-D image's resolution. Net k's pairs use one randomised
  ``physical`` model (gain, PSF, attenuation) drawn from ``STYLE_SEED_BASE + k``, its own probe
  poses (``rng_seed = k``) and its own init / batch order (``seed = k``). A deterministic
  generator cannot learn a gain it does not see in the CT, so randomising physics *within* a
  net's data only averages it away; randomising it *across* nets gives the set of different
  simulators the paper trains its policies over.
* ``train``: ``train_pix2pix`` with ``TRAIN`` settings, one net after the other.
* ``ship``: copies the generators to the package's ``weights/net{k}.pt`` (without local
  paths).
* ``card``: the model-card numbers (``sonogym.learned_training.model_card``) as JSON and a
  Markdown table.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

NUM_NETS = 5
IMAGE_SIZE = (100, 75)  # (depth, width) px
PIXEL_SPACING = 1e-3  # m
TRAIN_PHANTOMS = tuple(range(1000, 1005))
UNSEEN_PHANTOM = 1005
PAIRS_PER_NET = 600
UNSEEN_PAIRS = 48
STYLE_SEED_BASE = 100
TRAIN = dict(steps=1500, width=16, depth=4, batch_size=8, lr=1e-3, eval_every=500)


def data_dirs(work: Path, k: int) -> tuple[Path, Path]:
    return Path(work) / f"data/net{k}", Path(work) / f"data/net{k}-unseen"


def run_dir(work: Path, k: int) -> Path:
    return Path(work) / f"runs/net{k}"


def build_data(work: Path, nets=range(NUM_NETS), progress: bool = True) -> None:
    from sonogym.learned_training.data import write_default_pairs

    for k in nets:
        main, unseen = data_dirs(work, k)
        common = dict(
            image_size=IMAGE_SIZE,
            pixel_spacing=PIXEL_SPACING,
            model_seed=STYLE_SEED_BASE + k,
            progress=progress,
        )
        write_default_pairs(main, n=PAIRS_PER_NET, seeds=TRAIN_PHANTOMS, rng_seed=k, **common)
        write_default_pairs(
            unseen, n=UNSEEN_PAIRS, seeds=(UNSEEN_PHANTOM,), rng_seed=1000 + k,
            test_fraction=1.0, **common,
        )  # fmt: skip


def train_all(work: Path, nets=range(NUM_NETS), progress: bool = True) -> list[dict]:
    from sonogym.learned_training.train import train_pix2pix

    out = []
    for k in nets:
        t0 = time.time()
        m = train_pix2pix(data_dirs(work, k)[0], run_dir(work, k), seed=k, progress=progress,
                          **TRAIN)  # fmt: skip
        m["wall_s_total"] = round(time.time() - t0, 1)
        (run_dir(work, k) / "metrics.json").write_text(json.dumps(m, indent=1))
        out.append(m)
    return out


def ship(work: Path, dest: Path | None = None, nets=range(NUM_NETS)) -> list[Path]:
    """Copy the trained generators into the package (``dest``: default the shipped folder),
    replacing the local data path by the recipe's description."""
    from sonogym.ultrasound.learned.checkpoint import read_checkpoint, save_checkpoint
    from sonogym.ultrasound.learned.shipped import WEIGHTS_DIR

    dest = Path(dest or WEIGHTS_DIR)
    dest.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in nets:
        src = run_dir(work, k) / "generator.pt"
        ck = read_checkpoint(src)
        ck["data"] = (
            f"sonogym.learned_training.recipe net {k}: physical ultrasound model, style seed "
            f"{STYLE_SEED_BASE + k}, phantoms {TRAIN_PHANTOMS[0]}-{TRAIN_PHANTOMS[-1]}"
        )
        ck["net"] = k
        ck.setdefault("image_size", list(IMAGE_SIZE))
        path = dest / f"net{k}.pt"
        paths.append(save_checkpoint(path, ck))
    return paths
