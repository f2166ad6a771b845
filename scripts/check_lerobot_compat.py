#!/usr/bin/env python
"""Check that LeRobot's own reader opens a sonogym dataset with the same frames and values.

LeRobot cannot live in sonogym's environment (it pins torch < 2.11 and a huggingface-hub that
clashes with diffusers), so this check runs LeRobot's dataset code in a venv of its own:

    python3 -m venv /tmp/lerobot-venv
    /tmp/lerobot-venv/bin/pip install torch==2.13.0+cpu lerobot-dataset==0.4.4

(keep the ``+cpu`` tag: without it pip pulls the CUDA build of torch.) ``lerobot-dataset`` is
LeRobot 0.4.4's dataset code as a package (module ``ledataset``); a full ``lerobot`` install
(module ``lerobot``) works too. LeRobot imports ``torchvision.transforms.ToTensor`` (its only
torchvision use on this path), and torchvision's wheel does not load beside a CPU torch, so the
LeRobot side puts a small stand-in ``torchvision`` package on ``sys.path`` when the real one is
missing (written to a temp folder by this script).

Usage, from the repository root with sonogym's interpreter:

    PYTHONPATH=src python scripts/check_lerobot_compat.py \
        --lerobot-python /tmp/lerobot-venv/bin/python [DATASET]

Without DATASET it writes a synthetic navigation/surgery-like dataset (grey and RGB images,
state, action; several episodes over several data files) to a temp folder. It then reads every
frame with sonogym's reader and with ``LeRobotDataset(repo_id="local/x", root=DATASET)``, plus
action chunks with ``delta_timestamps`` (values and ``action_is_pad``), compares, prints what
it found and exits 0 when everything matched exactly, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CHUNK = 5  # action chunk length of the delta_timestamps comparison

TORCHVISION_STUB = '''"""Stand-in torchvision for LeRobot's read path: transforms.ToTensor."""
'''
TRANSFORMS_STUB = '''import numpy as np
import torch


class ToTensor:
    """PIL image (uint8, mode L or RGB) -> float (C, H, W) in [0, 1], as torchvision does."""

    def __call__(self, pic):
        a = np.asarray(pic)
        if a.ndim == 2:
            a = a[:, :, None]
        if a.dtype != np.uint8:
            raise TypeError(f"stub ToTensor handles uint8 images only, got {a.dtype}")
        return torch.from_numpy(a.transpose(2, 0, 1).copy()).float().div(255.0)
'''


# --- LeRobot side (runs in the LeRobot venv; imports no sonogym) -------------------------------


def dump_lerobot(root: str, out: str) -> None:
    try:
        import torchvision  # noqa: F401
    except Exception:
        stub = Path(tempfile.mkdtemp()) / "torchvision"
        stub.mkdir()
        (stub / "__init__.py").write_text(TORCHVISION_STUB + "from . import transforms  # noqa\n")
        (stub / "transforms.py").write_text(TRANSFORMS_STUB)
        sys.path.insert(0, str(stub.parent))
        for name in [m for m in sys.modules if m.startswith("torchvision")]:
            del sys.modules[name]
    from importlib import metadata

    try:
        from lerobot.datasets.lerobot_dataset import CODEBASE_VERSION, LeRobotDataset

        dist = "lerobot"
    except ImportError:
        from ledataset.datasets.lerobot_dataset import CODEBASE_VERSION, LeRobotDataset

        dist = "lerobot-dataset"
    ds = LeRobotDataset(repo_id="local/x", root=root)
    arrays: dict[str, list] = {}
    for i in range(len(ds)):
        for k, v in ds[i].items():
            if k != "task":
                arrays.setdefault(k, []).append(np.asarray(v))
    fps = ds.fps
    chunked = LeRobotDataset(
        repo_id="local/x", root=root, delta_timestamps={"action": [j / fps for j in range(CHUNK)]}
    )
    for i in range(len(chunked)):
        item = chunked[i]
        arrays.setdefault("chunk/action", []).append(np.asarray(item["action"]))
        arrays.setdefault("chunk/action_is_pad", []).append(np.asarray(item["action_is_pad"]))
    meta = {
        "dist": dist,
        "version": metadata.version(dist),
        "codebase_version": CODEBASE_VERSION,
        "len": len(ds),
        "num_episodes": ds.num_episodes,
        "task0": ds[0]["task"],
    }
    np.savez(out, meta=json.dumps(meta), **{k: np.stack(v) for k, v in arrays.items()})


# --- sonogym side --------------------------------------------------------------------------------


def write_synthetic(root: Path) -> None:
    from sonogym.imitation.writer import DatasetWriter

    features = {
        "observation.images.us": {"dtype": "image", "shape": [40, 30, 1], "names": None},
        "observation.images.slice_0": {"dtype": "image", "shape": [10, 8, 3], "names": None},
        "observation.state": {"dtype": "float32", "shape": [7], "names": None},
        "action": {"dtype": "float32", "shape": [3], "names": ["dx", "dz", "dyaw"]},
    }
    rng = np.random.default_rng(0)
    # every episode goes into a data file of its own: several data files
    with DatasetWriter(root, 30, features, task="navigate to L4") as w:
        for e in range(4):
            t = 6 + 3 * e
            w.add_episode(
                {
                    "observation.images.us": rng.random((t, 1, 40, 30), dtype=np.float32),
                    "observation.images.slice_0": rng.integers(0, 256, (t, 10, 8, 3), np.uint8),
                    "observation.state": rng.standard_normal((t, 7)).astype(np.float32),
                    "action": rng.standard_normal((t, 3)).astype(np.float32),
                },
                task="navigate to L4" if e < 3 else "second task",
            )


def read_ours(root: Path) -> dict[str, np.ndarray]:
    from sonogym.imitation.reader import LeRobotFrames

    ds = LeRobotFrames(root)
    out: dict[str, list] = {}
    for i in range(len(ds)):
        for k, v in ds[i].items():
            out.setdefault(k, []).append(v.numpy())
    chunked = LeRobotFrames(root, delta_indices={"action": list(range(CHUNK))})
    for i in range(len(chunked)):
        item = chunked[i]
        out.setdefault("chunk/action", []).append(item["action"].numpy())
        out.setdefault("chunk/action_is_pad", []).append(item["action_is_pad"].numpy())
    return {k: np.stack(v) for k, v in out.items()}


def compare(ours: dict[str, np.ndarray], theirs: dict[str, np.ndarray]) -> list[str]:
    problems = []
    for k in sorted(set(ours) | set(theirs)):
        if k not in ours or k not in theirs:
            problems.append(f"{k}: only in {'ours' if k in ours else 'LeRobot'}")
            continue
        a, b = (
            ours[k],
            theirs[k].reshape(ours[k].shape) if theirs[k].size == ours[k].size else theirs[k],
        )
        if a.shape != b.shape:
            problems.append(f"{k}: shape {a.shape} (ours) vs {b.shape} (LeRobot)")
        elif not np.array_equal(a.astype(np.float64), b.astype(np.float64)):
            diff = np.abs(a.astype(np.float64) - b.astype(np.float64)).max()
            problems.append(f"{k}: values differ (max abs diff {diff:.3g})")
        else:
            print(f"  {k:32s} {str(a.shape):22s} equal")
    return problems


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("dataset", nargs="?", help="dataset folder (default: write a synthetic one)")
    p.add_argument("--lerobot-python", help="python of the venv with lerobot-dataset installed")
    p.add_argument("--dump-lerobot", nargs=2, metavar=("ROOT", "OUT"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.dump_lerobot:
        dump_lerobot(*args.dump_lerobot)
        return 0
    if not args.lerobot_python:
        p.error("--lerobot-python is required (see the header for the venv set-up)")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.dataset) if args.dataset else Path(tmp) / "dataset"
        if not args.dataset:
            write_synthetic(root)
        out = Path(tmp) / "lerobot.npz"
        env = {
            **os.environ,
            "HF_HUB_OFFLINE": "1",
            "HF_DATASETS_CACHE": str(Path(tmp) / "hf-cache"),
            "HF_LEROBOT_HOME": str(Path(tmp) / "lerobot-home"),
            "PYTHONPATH": "",
        }
        subprocess.run(
            [args.lerobot_python, __file__, "--dump-lerobot", str(root), str(out)],
            check=True,
            env=env,
        )
        with np.load(out) as z:
            theirs = {k: z[k] for k in z.files if k != "meta"}
            meta = json.loads(str(z["meta"]))
        ours = read_ours(root)
        info = json.loads((root / "meta/info.json").read_text())
        print(
            f"LeRobot reader: {meta['dist']} {meta['version']} "
            f"(codebase {meta['codebase_version']})"
        )
        print(
            f"dataset {root}: info.json codebase {info['codebase_version']}, "
            f"{info['total_episodes']} episodes, {info['total_frames']} frames; LeRobot read "
            f"{meta['num_episodes']} episodes, {meta['len']} frames; first task {meta['task0']!r}"
        )
        problems = compare(ours, theirs)
        if meta["len"] != info["total_frames"]:
            problems.append(f"frame count: LeRobot {meta['len']}, info.json {info['total_frames']}")
    if problems:
        print("MISMATCH:\n  " + "\n  ".join(problems))
        return 1
    print("all values equal")
    return 0


if __name__ == "__main__":
    sys.exit(main())
