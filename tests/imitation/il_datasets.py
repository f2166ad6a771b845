"""Synthetic LeRobot datasets for the imitation tests (no env needed).

A module of its own, not conftest.py: several test folders have a conftest, and a plain
``from conftest import`` resolves to whichever was imported first."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from sonogym.imitation.writer import DatasetWriter

FPS = 10

FEATURES = {
    "observation.images.us": {"dtype": "image", "shape": [12, 9, 1], "names": None},
    "observation.images.rgb": {"dtype": "image", "shape": [6, 5, 3], "names": None},
    "observation.state": {"dtype": "float32", "shape": [2], "names": ["x", "z"]},
    "action": {"dtype": "float32", "shape": [3], "names": ["dx", "dz", "dyaw"]},
}


def random_episodes(n: int, seed: int = 0, lengths=None) -> list[dict[str, np.ndarray]]:
    """Episodes of FEATURES: grey float frames given (T, C, H, W), RGB uint8 (T, H, W, C)."""
    rng = np.random.default_rng(seed)
    out = []
    for e in range(n):
        t = lengths[e] if lengths is not None else 4 + 2 * e
        out.append(
            {
                "observation.images.us": rng.random((t, 1, 12, 9), dtype=np.float32),
                "observation.images.rgb": rng.integers(0, 256, (t, 6, 5, 3), dtype=np.uint8),
                "observation.state": rng.standard_normal((t, 2)).astype(np.float32),
                "action": rng.standard_normal((t, 3)).astype(np.float32),
            }
        )
    return out


def set_value(root, key: str, frame: int, component: int, value: float) -> Path:
    """Overwrite one value of a numeric feature of global frame ``frame`` in the data file that
    holds it, as a corrupt or hand-edited file holds it (the writer refuses NaN); returns the
    file."""
    for path in sorted((Path(root) / "data").glob("*/*.parquet")):
        t = pq.read_table(path)
        rows = np.flatnonzero(t.column("index").to_numpy() == frame)
        if len(rows):
            break
    else:
        raise AssertionError(f"no data file of {root} holds frame {frame}")
    a = np.asarray(t.column(key).combine_chunks().flatten()).reshape(len(t), -1).copy()
    a[rows[0], component] = value
    i = t.schema.get_field_index(key)
    flat = pa.array(a.reshape(-1), pa.float32())
    col = pa.FixedSizeListArray.from_arrays(flat, a.shape[1])
    pq.write_table(t.set_column(i, t.schema.field(i), col), path)
    return path


def write(root, episodes, **kw) -> DatasetWriter:
    w = DatasetWriter(root, FPS, FEATURES, task=kw.pop("task", "navigate"), **kw)
    for ep in episodes:
        w.add_episode(ep)
    return w


def blob_episodes(n: int, t: int = 24, h: int = 16, w: int = 12, seed: int = 0):
    """A learnable toy task: a bright square at the state's position moves toward the centre;
    the action is a fixed linear function of the state."""
    rng = np.random.default_rng(seed)
    eps = []
    for _ in range(n):
        pos = rng.uniform(-1, 1, 2)
        frames, states, actions = [], [], []
        for _ in range(t):
            img = np.zeros((1, h, w), np.float32)
            r, c = int((pos[0] + 1) / 2 * (h - 1)), int((pos[1] + 1) / 2 * (w - 1))
            img[0, max(r - 2, 0) : r + 3, max(c - 2, 0) : c + 3] = 1.0
            a = np.array([-0.2 * pos[0], -0.2 * pos[1], 0.1 * pos[0] * pos[1]], np.float32)
            frames.append(img)
            states.append(pos.astype(np.float32))
            actions.append(a)
            pos = pos + a[:2]
        eps.append(
            {
                "observation.images.cam": np.stack(frames),
                "observation.state": np.stack(states),
                "action": np.stack(actions),
            }
        )
    return eps


BLOB_FEATURES = {
    "observation.images.cam": {"dtype": "image", "shape": [16, 12, 1], "names": None},
    "observation.state": {"dtype": "float32", "shape": [2], "names": None},
    "action": {"dtype": "float32", "shape": [3], "names": None},
}
