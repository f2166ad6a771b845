"""Read LeRobotDataset v3.0 folders (ours or LeRobot's, images embedded as PNG) as torch data.

``LeRobotFrames`` is a ``torch.utils.data.Dataset`` over frames. An item is a dict of tensors:
images float32 (C, H, W) in [0, 1] (= uint8 / 255), numeric features (D,) in their dtype (shape
(1,) features as 0-d tensors, as LeRobot returns them), the bookkeeping features ``timestamp``
(s), ``frame_index``, ``episode_index``, ``index``, ``task_index``.

Observation history and action chunks, LeRobot's way: ``delta_indices={key: [d0, d1, ...]}``
(frames relative to the item's frame; or ``delta_timestamps`` in seconds, multiples of 1/fps)
returns ``key`` stacked as (K, ...) and ``key + "_is_pad"`` (K,) bool, True where frame
``t + d`` lies outside the item's episode; those entries repeat the episode's first or last
frame (LeRobot clamps the same way). ``drop_n_last_frames`` leaves the last frames of each
episode out of the items (Diffusion Policy's sampler does this), not out of the lookups.

Only frames with ``index < total_frames`` and episodes ``< total_episodes`` of ``info.json``
count: rows an interrupted writer left past them are ignored.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import torch

from sonogym.imitation import lerobot_format as fmt
from sonogym.memory import available_memory

BOOKKEEPING = tuple(fmt.DEFAULT_FEATURES)
#: Largest magnitude a numeric feature value (action, state, ...) or statistic may have, in the
#: feature's own units. No sonogym feature comes near it (actions are O(1) action units, states
#: metres and radians) nor does a robot's joint angle in degrees or position in mm; a value
#: beyond it, like NaN or inf, is a corrupt or mis-scaled frame that would train a policy to
#: NaN weights, so the reader refuses it.
MAX_ABS_VALUE = 1e6


def load_stats(root: str | Path) -> dict[str, dict[str, torch.Tensor]]:
    """``meta/stats.json`` as float32 tensors (images (C, 1, 1), vectors (D,), count (1,)).

    Refused with ``DatasetFormatError`` naming the file, feature and statistic: a feature of
    ``meta/info.json`` without statistics, statistics of another shape than the feature's (an
    info.json of another robot or task), and a non-finite value or one beyond
    ``MAX_ABS_VALUE``."""
    import json

    info = fmt.read_info(root)  # version check
    path = Path(root) / fmt.STATS_PATH
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: the dataset has no episodes yet?")
    try:
        raw = json.loads(path.read_text())
        out = {
            k: {
                s: torch.tensor(np.asarray(v, dtype=np.float64), dtype=torch.float32)
                for s, v in d.items()
            }
            for k, d in raw.items()
        }
    except (ValueError, TypeError, AttributeError) as e:  # not JSON, or not {key: {stat: list}}
        raise fmt.DatasetFormatError(
            f"{path} is not a LeRobot stats file ({e}); restore it or re-record the dataset"
        ) from None
    for key, ft in info["features"].items():
        if key in BOOKKEEPING:
            continue
        _check_stats(path, key, ft, out.get(key))
    return out


def _check_stats(path: Path, key: str, ft: dict[str, Any], stats: dict | None) -> None:
    fix = "restore the dataset's meta folder or re-record it"
    if stats is None:
        raise fmt.DatasetFormatError(
            f"{path} has no statistics of {key!r}, a feature of meta/info.json: the two files "
            f"describe different features (another robot's or task's?); {fix}"
        )
    shape = ft["shape"]
    want = (int(shape[2]), 1, 1) if fmt.is_image(ft) else (int(np.prod(shape)),)
    for name in ("min", "max", "mean", "std"):
        v = stats.get(name)
        if v is None or tuple(v.shape) != want:
            got = None if v is None else tuple(v.shape)
            raise fmt.DatasetFormatError(
                f"{path}: {key}/{name} has shape {got}, meta/info.json's {key} needs {want}: "
                f"the two files describe different features; {fix}"
            )
    for name, v in stats.items():
        if name == "count":
            continue
        bad = ~torch.isfinite(v) | (v.abs() > MAX_ABS_VALUE)
        if bool(bad.any()):
            raise fmt.DatasetFormatError(
                f"{path}: {key}/{name} holds {v[bad].flatten()[0].item()} (values must be finite "
                f"and within +-{MAX_ABS_VALUE:g}); {fix}"
            )


def read_episodes(root: str | Path, info: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Committed ``meta/episodes`` rows (without the ``stats/`` columns), by episode index."""
    info = fmt.read_info(root) if info is None else info
    n = int(info["total_episodes"])
    cols = [
        "episode_index",
        "tasks",
        "length",
        "data/chunk_index",
        "data/file_index",
        "dataset_from_index",
        "dataset_to_index",
    ]
    rows = []
    for path in sorted((Path(root) / fmt.EPISODES_DIR).glob("*/*.parquet")):
        rows += [r for r in pq.read_table(path, columns=cols).to_pylist() if r["episode_index"] < n]
    rows.sort(key=lambda r: r["episode_index"])
    if [r["episode_index"] for r in rows] != list(range(n)):
        raise fmt.DatasetFormatError(f"{root}: meta/episodes does not hold episodes 0..{n - 1}")
    return rows


def delta_timestamps_to_indices(
    delta_timestamps: dict[str, list[float]], fps: int, tolerance_s: float = 1e-4
) -> dict[str, list[int]]:
    """Seconds -> frame offsets, refusing deltas that are not multiples of 1/fps (± tolerance)."""
    out = {}
    for key, ds in delta_timestamps.items():
        idx = [round(d * fps) for d in ds]
        bad = [d for d, i in zip(ds, idx, strict=True) if abs(d - i / fps) > tolerance_s]
        if bad:
            raise ValueError(f"delta_timestamps[{key!r}]: {bad} are not multiples of 1/{fps} s")
        out[key] = idx
    return out


class LeRobotFrames(torch.utils.data.Dataset):
    """Frames of a LeRobotDataset v3.0 folder (see the module doc).

    Args:
        root: dataset folder.
        delta_indices / delta_timestamps: per-key frame offsets (or seconds) to stack (give one).
        episodes: episode indices whose frames are items (None: all); lookups stay inside them.
        drop_n_last_frames: frames at the end of each episode that are not items (>= 0).
        image_cache: "bytes" keeps the PNG bytes of the data files read (LRU, ``cache_mb``
            MiB), decoding on access; "decoded" decodes every image once at start (uint8 in
            memory, fastest for small datasets).
        cache_mb: memory budget of the "bytes" cache in MiB; None (default): the size of the
            data files on disk, so that each is read once, but at most half the memory
            available now. A budget smaller than the data files warns: random sampling then
            re-reads whole files (behind the old fixed 4 GiB budget, ACT on a 1,000-episode
            navigation dataset of 5.3 GB trained at ~3 it/s; sized to fit, ~16 it/s).
    """

    def __init__(
        self,
        root: str | Path,
        delta_indices: dict[str, list[int]] | None = None,
        delta_timestamps: dict[str, list[float]] | None = None,
        episodes: list[int] | None = None,
        drop_n_last_frames: int = 0,
        image_cache: str = "bytes",
        cache_mb: float | None = None,
    ) -> None:
        self.root = Path(root)
        self.info = fmt.read_info(root)
        self.features = {
            k: {**v, "shape": [int(s) for s in v["shape"]]}
            for k, v in self.info["features"].items()
        }
        self.fps = int(self.info["fps"])
        if delta_indices is not None and delta_timestamps is not None:
            raise ValueError("give delta_indices or delta_timestamps, not both")
        if delta_timestamps is not None:
            delta_indices = delta_timestamps_to_indices(delta_timestamps, self.fps)
        self.delta_indices = {k: [int(d) for d in v] for k, v in (delta_indices or {}).items()}
        unknown = set(self.delta_indices) - set(self.features)
        if unknown:
            raise KeyError(f"delta keys {sorted(unknown)} are not features of {root}")
        if drop_n_last_frames < 0:
            raise ValueError(f"drop_n_last_frames must be >= 0, got {drop_n_last_frames}")
        if image_cache not in ("bytes", "decoded"):
            raise ValueError(f"image_cache must be 'bytes' or 'decoded', got {image_cache!r}")
        self.image_keys = [k for k, ft in self.features.items() if fmt.is_image(ft)]
        self.episodes = read_episodes(root, self.info)
        self._load_columns()
        # frame -> its episode's [from, to)
        ep_from = torch.tensor([e["dataset_from_index"] for e in self.episodes], dtype=torch.long)
        ep_to = torch.tensor([e["dataset_to_index"] for e in self.episodes], dtype=torch.long)
        ep_of = self._numeric["episode_index"].long()
        self._from, self._to = ep_from[ep_of], ep_to[ep_of]
        chosen = range(len(self.episodes)) if episodes is None else episodes
        items = []
        for e in chosen:
            if not 0 <= e < len(self.episodes):
                raise IndexError(f"episode {e} not in {root} ({len(self.episodes)} episodes)")
            lo, hi = self.episodes[e]["dataset_from_index"], self.episodes[e]["dataset_to_index"]
            items.append(torch.arange(lo, max(lo, hi - drop_n_last_frames)))
        self._items = torch.cat(items) if items else torch.zeros(0, dtype=torch.long)
        self._cache: OrderedDict[int, dict[str, list[bytes]]] = OrderedDict()
        self._cache_bytes = 0
        self._cache_limit = self._cache_budget(cache_mb) if image_cache == "bytes" else 0
        self._decoded: dict[str, torch.Tensor] | None = None
        if image_cache == "decoded" and self.image_keys:
            self._decoded = {k: self._decode_all(k) for k in self.image_keys}

    # --- loading ----------------------------------------------------------------------------

    def _load_columns(self) -> None:
        """Numeric columns of every committed frame, and where each frame's row lives."""
        total = int(self.info["total_frames"])
        self._files = sorted((self.root / fmt.DATA_DIR).glob("*/*.parquet"))
        numeric = [k for k in self.features if k not in self.image_keys]
        parts: dict[str, list[np.ndarray]] = {k: [] for k in numeric}
        file_of, row_of = [], []
        for fi, path in enumerate(self._files):
            t = pq.read_table(path, columns=numeric)
            index = t.column("index").to_numpy()
            keep = index < total
            for k in numeric:
                col = t.column(k)
                ft = self.features[k]
                if ft["shape"] == [1]:
                    arr = col.to_numpy()
                else:
                    arr = np.asarray(col.combine_chunks().flatten()).reshape(len(t), -1)
                    if arr.shape[1] != int(np.prod(ft["shape"])):
                        raise fmt.DatasetFormatError(
                            f"{path}: column {k!r} holds {arr.shape[1]} values per frame, but "
                            f"meta/info.json declares shape {ft['shape']}: info.json does not "
                            "describe this data (edited, or another dataset's); restore it or "
                            "re-record the dataset"
                        )
                parts[k].append(arr[keep])
            self._check_values(path, {k: parts[k][-1] for k in numeric})
            file_of.append(np.full(int(keep.sum()), fi))
            row_of.append(np.flatnonzero(keep))
        if not self._files:
            raise FileNotFoundError(f"{self.root / fmt.DATA_DIR}: no data files")
        index = np.concatenate(parts["index"])
        if not np.array_equal(index, np.arange(total)):
            raise fmt.DatasetFormatError(
                f"{self.root}: data rows do not hold frame indices 0..{total - 1} in order "
                f"({len(index)} rows read)"
            )
        self._numeric: dict[str, torch.Tensor] = {}
        for k in numeric:
            arr = np.concatenate(parts[k]).astype(self.features[k]["dtype"])
            self._numeric[k] = torch.from_numpy(np.ascontiguousarray(arr))
        self._file_of = np.concatenate(file_of)
        self._row_of = np.concatenate(row_of)

    @staticmethod
    def _check_values(path: Path, cols: dict[str, np.ndarray]) -> None:
        """Refuse NaN, inf and values beyond ``MAX_ABS_VALUE`` in the float columns ``cols``
        (one data file's committed rows), naming the file, episode, frame and column."""
        for k, arr in cols.items():
            if not np.issubdtype(arr.dtype, np.floating) or arr.size == 0:
                continue  # (a file of an uncommitted episode keeps no rows)
            bad = (~np.isfinite(arr) | (np.abs(arr) > MAX_ABS_VALUE)).reshape(len(arr), -1)
            if not bad.any():
                continue
            row, j = (int(i[0]) for i in np.nonzero(bad))
            value = arr.reshape(len(arr), -1)[row, j]
            where = f"{k}[{j}]" if arr.ndim > 1 else k
            raise fmt.DatasetFormatError(
                f"{path}: episode {cols['episode_index'][row]}, frame "
                f"{cols['frame_index'][row]}, column {where} is {value:.6g} (values must be finite "
                f"and within +-{MAX_ABS_VALUE:g}): a corrupt or mis-scaled frame; fix or drop "
                "that episode, or re-record the dataset"
            )

    def _cache_budget(self, cache_mb: float | None) -> float:
        """Bytes the "bytes" cache may hold (see ``cache_mb``); warns when the data files do
        not fit."""
        need = sum(f.stat().st_size for f in self._files)
        if cache_mb is not None:
            budget, why = float(cache_mb) * 2**20, f"cache_mb={cache_mb:g}"
        else:
            budget, why = float(need), "the data files' size"
            avail = available_memory()
            if avail is not None and avail / 2 < need:
                budget, why = avail / 2, "half the memory available"
        if self.image_keys and budget < need:
            warnings.warn(
                f"{self.root}: its data files ({need / 2**30:.2f} GiB) do not fit the image "
                f"cache ({budget / 2**30:.2f} GiB, {why}): random sampling will re-read whole "
                "files, which can slow training several-fold; free memory, give a larger "
                "cache_mb, or train on fewer episodes",
                stacklevel=3,
            )
        return budget

    def _file_images(self, fi: int) -> dict[str, list[bytes]]:
        got = self._cache.get(fi)
        if got is not None:
            self._cache.move_to_end(fi)
            return got
        t = pq.read_table(self._files[fi], columns=self.image_keys)
        got = {k: t.column(k).combine_chunks().field("bytes").to_pylist() for k in self.image_keys}
        size = sum(len(b) for v in got.values() for b in v)
        self._cache[fi] = got
        self._cache_bytes += size
        while self._cache_bytes > self._cache_limit and len(self._cache) > 1:
            _, old = self._cache.popitem(last=False)
            self._cache_bytes -= sum(len(b) for v in old.values() for b in v)
        return got

    def _decode(self, key: str, idx: int) -> torch.Tensor:
        """uint8 (C, H, W) of frame ``idx``."""
        if self._decoded is not None:
            return self._decoded[key][idx]
        data = self._file_images(int(self._file_of[idx]))[key][int(self._row_of[idx])]
        try:
            arr = fmt.decode_png(data)
        except Exception as e:  # PIL raises several types for damaged bytes
            raise fmt.DatasetFormatError(
                f"{self._where(key, idx)}: the PNG does not decode ({type(e).__name__}: {e}); "
                "the data file is damaged: restore it, or record the dataset again"
            ) from None
        if list(arr.shape) != self.features[key]["shape"]:
            raise fmt.DatasetFormatError(
                f"{self._where(key, idx)}: PNG of shape {arr.shape}, info.json says "
                f"{self.features[key]['shape']}"
            )
        return torch.from_numpy(arr.transpose(2, 0, 1).copy())

    def _where(self, key: str, idx: int) -> str:
        """Where frame ``idx``'s ``key`` is stored, for error messages."""
        return (
            f"{self._files[int(self._file_of[idx])]} (row {int(self._row_of[idx])}): episode "
            f"{int(self._numeric['episode_index'][idx])}, frame "
            f"{int(self._numeric['frame_index'][idx])} (index {idx}), key {key!r}"
        )

    def _decode_all(self, key: str) -> torch.Tensor:
        h, w, c = self.features[key]["shape"]
        out = torch.empty(len(self._file_of), c, h, w, dtype=torch.uint8)
        for idx in range(len(self._file_of)):
            out[idx] = self._decode(key, idx)
        self._cache.clear()
        self._cache_bytes = 0
        return out

    # --- Dataset ----------------------------------------------------------------------------

    @property
    def num_frames(self) -> int:
        return int(self.info["total_frames"])

    def __len__(self) -> int:
        return len(self._items)

    def _value(self, key: str, idx: int) -> torch.Tensor:
        if key in self.image_keys:
            return self._decode(key, idx).float() / 255.0
        return self._numeric[key][idx]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        idx = int(self._items[i])
        lo, hi = int(self._from[idx]), int(self._to[idx])
        item: dict[str, torch.Tensor] = {}
        for key in self.features:
            deltas = self.delta_indices.get(key)
            if deltas is None:
                item[key] = self._value(key, idx)
                continue
            q = [idx + d for d in deltas]
            item[key + "_is_pad"] = torch.tensor([not lo <= j < hi for j in q])
            item[key] = torch.stack([self._value(key, min(max(j, lo), hi - 1)) for j in q])
        return item

    def frame(self, index: int) -> dict[str, torch.Tensor]:
        """Frame ``index`` (global frame index) without deltas."""
        return {k: self._value(k, int(index)) for k in self.features}
