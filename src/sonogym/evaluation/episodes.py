"""Per-episode evaluation logs: what ``sonogym eval`` saw, episode by episode, so that tables and
figures can be regenerated without rerunning anything.

A log is ``<run>/episodes/<protocol>.npz`` (NumPy, no pickles) holding:

* ``meta``: a JSON string: ``format`` (1), ``task``, ``algo``, ``run`` (folder name),
  ``train_seed``, ``protocol``, ``eval_seed``, ``trials``, ``num_envs`` (episode k ran in env
  k % num_envs, so on the test env's patient (k % num_envs) % P; absent in logs written
  before it was recorded), ``controllers``, ``checkpoint``,
  ``train_env`` / ``test_env`` (the env options of training and of this test),
  ``track_columns`` and ``track_units``;
* ``<controller>/<metric>``: (trials,) float32, the task's episode metrics (``return``
  included) in the env's units (``safe_ratio`` a fraction);
* ``<controller>/track``: (trials, T + 1, D) float32, the tracked point from the start state to
  the last state (the task's ``TaskSpec.track``).

Controllers are ``policy``, ``expert`` (the task's expert or heuristic) and ``random``. An
imitation-learning run can join the report by writing the same file under its own run folder
(its ``config.json`` naming ``task`` and ``algo``, e.g. ``act``).
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sonogym.envs.registry import get_task
from sonogym.envs.rollout import rollout
from sonogym.runs import atomic_write_bytes

FORMAT = 1


def run_episodes(
    env, policy, trials: int, seed: int, task: str, progress: Any = None
) -> dict[str, Any]:
    """``trials`` episodes of ``policy`` in ``env`` (batches of ``env.num_envs`` fixed-length
    episodes from ``env.reset(seed=seed)``): {"metrics": {metric: (trials,) array},
    "track": (trials, T + 1, D) array} with the task's tracked point (``TaskSpec.track``) from
    each start state to its last state. ``progress``: a progress display
    (``sonogym.progress.progress_bar`` over ``episode_steps(env, trials)``), advanced each env
    step and told the episodes done after each batch."""
    track = get_task(task).track
    n, T = env.num_envs, env.episode_length
    batches = math.ceil(trials / n)
    collected: dict[str, list[torch.Tensor]] = {}
    paths = torch.zeros(batches * n, T + 1, len(track.columns))
    for step in rollout(env, policy, batches * T, seed=seed):
        b, t = divmod(step.t, T)
        rows = slice(b * n, (b + 1) * n)
        if t == 0:
            paths[rows, 0] = track.fn(env, step.info).float().cpu()
        paths[rows, t + 1] = track.fn(env, step.next_info).float().cpu()
        final = step.final_info
        if final is not None:
            if t != T - 1 or len(final["env_ids"]) != n:
                raise RuntimeError(
                    f"{task}: episodes ended out of step (step {t + 1} of {T}, "
                    f"{len(final['env_ids'])} of {n} envs); the log assumes fixed-length episodes"
                )
            order = torch.argsort(final["env_ids"].cpu())
            for k, v in final.items():
                if k != "env_ids":
                    collected.setdefault(k, []).append(v.detach().float().cpu()[order])
            if progress is not None:
                progress.set_postfix(**{"episodes done": f"{min((b + 1) * n, trials)}/{trials}"})
        if progress is not None:
            progress.update(1)
    return {
        "metrics": {k: torch.cat(v)[:trials].numpy() for k, v in collected.items()},
        "track": paths[:trials].numpy(),
    }


def episode_steps(env, trials: int) -> int:
    """The env steps ``run_episodes`` takes for ``trials`` episodes (whole batches)."""
    return math.ceil(trials / env.num_envs) * env.episode_length


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
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())
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
    h, v = get_task(task).track.plane
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
        if get_task(task).track.axis_line:
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
        return get_task(meta["task"]).expert_label
    return c


def episode_patient(log: EpisodeLog, episode: int) -> int | str:
    """The test patient episode ``episode`` ran on: env k % num_envs of the evaluation, which
    holds patient (k % num_envs) % P."""
    meta = log.meta
    default = get_task(meta["task"]).config_cls().patients
    patients = list(meta.get("test_env", {}).get("patients", default))
    if len(patients) == 1:
        return patients[0]
    n = meta.get("num_envs")
    if n is None:
        raise ValueError(
            f"{log.path}: its episodes ran on {len(patients)} patients and the log does not say "
            "how many envs ran them (it predates that field): evaluate the run again "
            "(sonogym eval) to place its episodes"
        )
    return patients[(episode % int(n)) % len(patients)]
