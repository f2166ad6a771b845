"""Feature statistics of a LeRobotDataset: per episode (``meta/episodes`` ``stats/...`` columns)
and over the dataset (``meta/stats.json``), with LeRobot 0.4's keys and shapes.

Per episode (exact, every frame and pixel; LeRobot samples up to 100 frames instead):
``min``, ``max``, ``mean``, ``std`` (population), ``count`` (frames, shape (1,)) and the quantiles
``q01 q10 q50 q90 q99`` (numpy's linear interpolation). Numeric features: shape (D,), min/max
in the feature's dtype. Images: per channel, shape (C, 1, 1), in [0, 1] (uint8 / 255), from a
256-bin histogram per channel.

Over the dataset (LeRobot's ``aggregate_stats`` rule): min/max of the episodes' min/max; mean
and std pooled exactly from the episodes' counts, means and variances; ``count`` the total
frames; each quantile the count-weighted mean of the episodes' quantiles (LeRobot's
approximation: exact for one episode, otherwise an average, not a quantile of the pooled data).
The aggregate is a function of the per-episode rows only, so a resumed writer rebuilds it from
``meta/episodes`` without reading frames again.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sonogym.imitation.lerobot_format import QUANTILE_KEYS, QUANTILES, is_image

STAT_KEYS = ("min", "max", "mean", "std", "count", *QUANTILE_KEYS)


def _hist_quantiles(hist: np.ndarray, qs: tuple[float, ...]) -> np.ndarray:
    """Quantiles of integer samples 0..255 given by their histogram, as np.quantile (linear)."""
    n = int(hist.sum())
    cum = np.cumsum(hist)
    out = []
    for q in qs:
        pos = q * (n - 1)
        lo, hi = int(np.floor(pos)), int(np.ceil(pos))
        v_lo = int(np.searchsorted(cum, lo, side="right"))  # value of the lo-th sorted sample
        v_hi = int(np.searchsorted(cum, hi, side="right"))
        out.append(v_lo + (pos - lo) * (v_hi - v_lo))
    return np.asarray(out, dtype=np.float64)


def image_episode_stats(frames_hwc: np.ndarray) -> dict[str, np.ndarray]:
    """Stats of one episode's uint8 frames (T, H, W, C): per channel, (C, 1, 1), in [0, 1]."""
    t, _, _, c = frames_hwc.shape
    flat = frames_hwc.reshape(-1, c)
    stats: dict[str, list] = {k: [] for k in STAT_KEYS if k != "count"}
    values = np.arange(256, dtype=np.float64)
    for ch in range(c):
        hist = np.bincount(flat[:, ch], minlength=256).astype(np.int64)
        n = hist.sum()
        nz = np.flatnonzero(hist)
        mean = (hist * values).sum() / n
        var = (hist * (values - mean) ** 2).sum() / n
        stats["min"].append(nz[0])
        stats["max"].append(nz[-1])
        stats["mean"].append(mean)
        stats["std"].append(np.sqrt(var))
        for key, qv in zip(QUANTILE_KEYS, _hist_quantiles(hist, QUANTILES), strict=True):
            stats[key].append(qv)
    out = {k: (np.asarray(v, dtype=np.float64) / 255.0).reshape(c, 1, 1) for k, v in stats.items()}
    out["count"] = np.array([t], dtype=np.int64)
    return out


def numeric_episode_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """Stats of one episode's numeric feature (T, D) (or (T,) for a scalar column): shape (D,)."""
    v = values.reshape(len(values), -1)
    v64 = v.astype(np.float64)
    out = {
        "min": v.min(axis=0),
        "max": v.max(axis=0),
        "mean": v64.mean(axis=0),
        "std": v64.std(axis=0),
        "count": np.array([len(v)], dtype=np.int64),
    }
    qv = np.quantile(v64, QUANTILES, axis=0)
    for i, key in enumerate(QUANTILE_KEYS):
        out[key] = qv[i]
    if not np.issubdtype(v.dtype, np.integer):
        out["min"], out["max"] = out["min"].astype(np.float64), out["max"].astype(np.float64)
    return out


def episode_stats(
    columns: dict[str, np.ndarray], features: dict[str, dict[str, Any]]
) -> dict[str, dict[str, np.ndarray]]:
    """Per-feature stats of one episode; ``columns[key]`` is (T, H, W, C) uint8 for images and
    (T, D) / (T,) for numeric features."""
    return {
        key: image_episode_stats(columns[key])
        if is_image(ft)
        else numeric_episode_stats(columns[key])
        for key, ft in features.items()
    }


class StatsAggregator:
    """Running dataset-level stats over episodes (LeRobot's aggregation rule, see module doc)."""

    def __init__(self) -> None:
        self._acc: dict[str, dict[str, Any]] = {}

    def add(self, ep: dict[str, dict[str, np.ndarray]]) -> None:
        for key, s in ep.items():
            c = float(s["count"][0])
            mean = np.asarray(s["mean"], np.float64)
            second = np.asarray(s["std"], np.float64) ** 2 + mean**2
            a = self._acc.get(key)
            if a is None:
                self._acc[key] = a = {
                    "n": 0,
                    "s1": np.zeros_like(mean),
                    "s2": np.zeros_like(mean),
                    "min": np.asarray(s["min"]),
                    "max": np.asarray(s["max"]),
                    **{q: np.zeros_like(mean) for q in QUANTILE_KEYS},
                }
            else:
                a["min"] = np.minimum(a["min"], s["min"])
                a["max"] = np.maximum(a["max"], s["max"])
            a["n"] += int(s["count"][0])
            a["s1"] = a["s1"] + c * mean
            a["s2"] = a["s2"] + c * second
            for q in QUANTILE_KEYS:
                a[q] = a[q] + c * np.asarray(s[q], np.float64)

    def result(self) -> dict[str, dict[str, np.ndarray]]:
        out = {}
        for key, a in self._acc.items():
            n = a["n"]
            mean = a["s1"] / n
            out[key] = {
                "min": a["min"],
                "max": a["max"],
                "mean": mean,
                "std": np.sqrt(np.maximum(a["s2"] / n - mean**2, 0.0)),
                "count": np.array([n], dtype=np.int64),
                **{q: a[q] / n for q in QUANTILE_KEYS},
            }
        return out


def to_json(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    """stats.json form: nested lists (images (C, 1, 1), vectors (D,), count (1,))."""
    return {k: {s: np.asarray(v).tolist() for s, v in d.items()} for k, d in stats.items()}


def flatten_episode_stats(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, Any]:
    """``{"stats/<key>/<stat>": nested list}``, the ``meta/episodes`` column form."""
    return {
        f"stats/{key}/{name}": np.asarray(v).tolist()
        for key, d in stats.items()
        for name, v in d.items()
    }


def unflatten_episode_stats(row: dict[str, Any]) -> dict[str, dict[str, np.ndarray]]:
    """Inverse of ``flatten_episode_stats`` for one ``meta/episodes`` row."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for col, v in row.items():
        if col.startswith("stats/"):
            key, name = col[len("stats/") :].rsplit("/", 1)
            out.setdefault(key, {})[name] = np.asarray(v)
    return out
