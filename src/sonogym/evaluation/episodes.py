"""Per-episode evaluation logs: what ``sonogym eval`` saw, episode by episode, so that tables and
figures can be regenerated without rerunning anything.

A log is ``<run>/episodes/<protocol>.npz`` (NumPy, no pickles) holding:

* ``meta``: a JSON string: ``format`` (1), ``task``, ``algo``, ``run`` (folder name),
  ``train_seed``, ``protocol``, ``eval_seed``, ``trials``, ``controllers``, ``checkpoint``,
  ``train_env`` / ``test_env`` (the env options of training and of this test),
  ``track_columns`` and ``track_units``;
* ``<controller>/<metric>``: (trials,) float32, the task's episode metrics (``return``
  included) in the env's units (``safe_ratio`` a fraction);
* ``<controller>/track``: (trials, T + 1, D) float32, the tracked point from the start state to
  the last state (see ``TRACKS``).

Controllers are ``policy``, ``expert`` (the task's expert or heuristic) and ``random``. An
imitation-learning run can join the report by writing the same file under its own run folder
(its ``config.json`` naming ``task`` and ``algo``, e.g. ``act``).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

FORMAT = 1


@dataclass(frozen=True)
class Track:
    """What trajectory a task logs: ``fn(env, info)`` -> (N, D) float, in ``units``."""

    columns: tuple[str, ...]
    units: tuple[str, ...]
    fn: Callable[[Any, dict], torch.Tensor]


def _probe_pose(env, info) -> torch.Tensor:
    """The reached probe pose as a surface command (x, z, yaw, tilt) relative to the env's goal
    command: x, z in mm (patient frame, frontal plane), yaw and tilt in deg.

    Rebuilt from ``info["state"]`` (the probe's pose in the task frame, measured before an
    in-step reset), so the last point of an episode is the pose its metrics were taken at."""
    from sonogym.geometry import matrix_from_axis_angle, wrap_angle

    state = info["state"].float()
    if hasattr(env, "_v_pos"):  # reconstruction: {U} in the vertebra frame {V}
        frame_pos, frame_rot = env._v_pos, env._v_rot
    else:  # navigation: {U} in the goal frame {G}
        frame_pos, frame_rot = env.goal_pos, env.goal_rot
    pos = frame_pos + (frame_rot @ state[:, :3].unsqueeze(-1)).squeeze(-1)
    rot = frame_rot @ matrix_from_axis_angle(state[:, 3:6])
    x, z, yaw, tilt = env.scene.skin.command_from_pose(pos, rot, env.scene.patient_index)
    g = env.goal_cmd
    out = [(x - g[:, 0]) * 1e3, (z - g[:, 1]) * 1e3, torch.rad2deg(wrap_angle(yaw - g[:, 2]))]
    if g.shape[1] > 3:
        out.append(torch.rad2deg(tilt - g[:, 3]))
    return torch.stack(out, -1)


def _drill_tip(env, info) -> torch.Tensor:
    """Drill tip in the goal frame {G} (mm): z along the planned trajectory, 0 at the target."""
    return info["state"][:, :3] * 1e3


#: Tracked trajectory per task.
TRACKS: dict[str, Track] = {
    "navigation": Track(("x", "z", "yaw"), ("mm", "mm", "deg"), _probe_pose),
    "reconstruction": Track(("x", "z", "yaw", "tilt"), ("mm", "mm", "deg", "deg"), _probe_pose),
    "surgery": Track(("x", "y", "z"), ("mm", "mm", "mm"), _drill_tip),
}


def current_info(env) -> dict:
    """The env's info for its current state (the start state right after a reset)."""
    return env._get_info()


def log_path(run: str | Path, protocol: str) -> Path:
    return Path(run) / "episodes" / f"{protocol}.npz"


def save_log(
    path: str | Path,
    meta: dict[str, Any],
    metrics: dict[str, dict[str, np.ndarray]],
    tracks: dict[str, np.ndarray],
) -> Path:
    """Write one log (see the module doc); ``metrics[controller][metric]`` (trials,),
    ``tracks[controller]`` (trials, T + 1, D)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, np.ndarray] = {
        "meta": np.array(json.dumps({"format": FORMAT, **meta}, sort_keys=True))
    }
    for c, m in metrics.items():
        for k, v in m.items():
            arrays[f"{c}/{k}"] = np.asarray(v, np.float32)
    for c, t in tracks.items():
        arrays[f"{c}/track"] = np.asarray(t, np.float32)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)
    return path


@dataclass(frozen=True)
class EpisodeLog:
    """A loaded log: ``meta``, ``metrics[controller][metric]``, ``tracks[controller]``."""

    path: Path
    meta: dict[str, Any]
    metrics: dict[str, dict[str, np.ndarray]]
    tracks: dict[str, np.ndarray]


def load_log(path: str | Path) -> EpisodeLog:
    path = Path(path)
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        if meta.get("format") != FORMAT:
            raise ValueError(f"{path}: episode-log format {meta.get('format')} != {FORMAT}")
        metrics: dict[str, dict[str, np.ndarray]] = {}
        tracks: dict[str, np.ndarray] = {}
        for key in z.files:
            if key == "meta":
                continue
            c, k = key.split("/", 1)
            if k == "track":
                tracks[c] = z[key]
            else:
                metrics.setdefault(c, {})[k] = z[key]
    return EpisodeLog(path, meta, metrics, tracks)


def run_logs(run: str | Path) -> list[EpisodeLog]:
    """Every episode log of a run, by protocol name."""
    return [load_log(p) for p in sorted((Path(run) / "episodes").glob("*.npz"))]


# ----------------------------------------------------------------------------- figure

#: Which two track columns a task's trajectory figure draws (horizontal, vertical).
PLANE = {"navigation": ("x", "z"), "reconstruction": ("x", "z"), "surgery": ("x", "z")}


def plot_trajectories(
    log: EpisodeLog,
    path: str | Path,
    controllers: tuple[str, ...] | None = None,
    episodes: int = 8,
    title: str | None = None,
) -> Path:
    """One panel per controller: the first ``episodes`` tracked paths in the task's plane
    (start o, end x), the goal at the origin. The title names the run, seed and protocol."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    task = log.meta["task"]
    cols = log.meta["track_columns"]
    units = log.meta["track_units"]
    h, v = PLANE[task]
    i, j = cols.index(h), cols.index(v)
    names = [c for c in (controllers or tuple(log.tracks)) if c in log.tracks]
    fig, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names), 3.8), squeeze=False)
    for ax, c in zip(axes[0], names, strict=True):
        tr = log.tracks[c][:episodes]
        for k, p in enumerate(tr):
            color = plt.cm.tab10(k % 10)
            ax.plot(p[:, i], p[:, j], "-", lw=1, color=color)
            ax.plot(p[0, i], p[0, j], "o", ms=3, color=color)
            ax.plot(p[-1, i], p[-1, j], "x", ms=5, color=color)
        ax.plot(0, 0, "*", ms=12, color="red", label="goal")
        if task == "surgery":
            ax.axvline(0, color="grey", lw=0.6, ls="--")  # the planned trajectory
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{h} [{units[i]}]")
        ax.set_ylabel(f"{v} [{units[j]}]")
        ax.set_title(_controller_label(c, log.meta))
    m = log.meta
    fig.suptitle(
        title
        or f"{task}: {len(tr)} of {m['trials']} episodes, protocol {m['protocol']}, "
        f"run {m['run']} (algo {m['algo']}, seed {m['train_seed']}), eval seed {m['eval_seed']}",
        fontsize=8,
    )
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)
    return path


def _controller_label(c: str, meta: dict) -> str:
    if c == "policy":
        return f"policy ({meta['algo']})"
    if c == "expert":
        return "heuristic" if meta["task"] == "reconstruction" else "expert"
    return c
