"""Evaluate a trained run (RL or imitation learning) against the task's expert and a random
policy.

``evaluate_run(run_dir, trials)`` rebuilds the run's env (its ``config.json`` env options,
optionally overridden), runs ``trials`` episodes for each controller from the same seeded
starts and returns the task's metrics (mean and std over episodes):

* ``policy``: the run's newest checkpoint: an RL run deterministically (the Gaussian's mean
  action), as its algorithm acts (``AlgorithmSpec.acting``: a ``ppo-sf`` run through its
  safety filter, and also ``unfiltered`` without it), an IL run as ``ILPolicy`` (ACT's
  temporal ensemble, Diffusion Policy's denoising);
* ``expert``: the task's expert (navigation, surgery) or heuristic raster (reconstruction),
  from the privileged ``info``, as ``sonogym demo`` runs it;
* ``random``: actions uniform in the env's action box, from a seeded generator.

The table is written to ``<run>/eval.json`` and ``<run>/eval.md`` (``eval-<protocol>.*`` for
the out-of-domain protocols), every episode's metrics and trajectory to
``<run>/episodes/<protocol>.npz`` (``sonogym.evaluation.episodes``) and a trajectory figure to
``<run>/trajectories-<protocol>.png``; ``out`` puts them into another folder instead (a run
that cannot be written to). That the folder takes them is checked before any episode runs.
"""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sonogym.evaluation.selection import resolve_checkpoint
from sonogym.evaluation.trained import TrainedRun, load_run, newest_checkpoint, run_policy
from sonogym.runs import atomic_write_text, to_jsonable

CONTROLLERS = ("policy", "expert", "random")
#: Parallel envs of an evaluation unless given (at most one per trial).
DEFAULT_ENVS = 16


def table_stem(name: str) -> str:
    """The file stem of evaluation ``name``'s table: ``eval`` for ``idt``, else
    ``eval-<name>``."""
    return "eval" if name == "idt" else f"eval-{name}"


def evaluate_run(
    run: str | Path,
    trials: int | None = None,
    envs: int | None = None,
    seed: int | None = None,
    device: str = "cpu",
    env_overrides: dict[str, Any] | None = None,
    controllers: tuple[str, ...] = CONTROLLERS,
    protocol: str | None = None,
    held_out_patients: int = 1,
    plot: bool = True,
    checkpoint: str | Path | None = None,
    safety_filter: dict[str, Any] | None = None,
    name: str | None = None,
    out: str | Path | None = None,
    progress: bool = False,
) -> dict[str, dict[str, tuple[float, float]]]:
    """{controller: {metric: (mean, std)}} over ``trials`` episodes each (see module doc).

    ``run``: an RL run (``sonogym train``) or an IL run (``sonogym il-train``, on a dataset
    ``sonogym record`` wrote). ``checkpoint``: the checkpoint to evaluate (``"selected"``: the
    one ``sonogym select`` chose; default: the run's newest readable one; an unreadable newer
    RL checkpoint is skipped with a warning naming it). ``controllers``: by default the
    policy, the controllers its algorithm adds (a ``ppo-sf`` run's ``unfiltered``), the expert
    and random. ``safety_filter``: test-time
    settings of the run's algorithm (``Acting.settings``; a ``ppo-sf`` run's filter, keys
    ``mode`` ("search" / "zero") and/or ``threshold``; default: the run's); the filter acts
    only at test time, so one trained run can be tested with several.

    ``protocol``: ``idt`` (default), ``odt-sim`` or ``odt-patient``
    (``sonogym.evaluation.protocols``): its test env options override the run's own, and its
    trials (100) and seed (1000) are the defaults. ``env_overrides`` may add other env options
    (not the protocol's). Without a protocol but with overrides the log is named ``custom``;
    ``name`` names it instead (e.g. one log per set of test patients).

    Writes ``eval.json`` / ``eval.md`` (``eval-<protocol>.*`` for other than ``idt``), the
    per-episode log ``episodes/<protocol>.npz`` and, with ``plot``, the trajectory figure
    ``trajectories-<protocol>.png`` into ``out`` (default: the run folder), which must be
    writable: checked before the episodes run. ``progress``: show the env's patients loading
    and the episodes on stderr.
    """
    from sonogym.evaluation.protocols import PROTOCOL_KEYS
    from sonogym.evaluation.protocols import protocol as get_protocol

    if name is not None and (not re.fullmatch(r"[A-Za-z0-9_.-]+", name) or name in (".", "..")):
        raise ValueError(f"name {name!r}: use letters, digits, '_' and '-' only")
    trained = load_run(run)
    controllers = check_controllers(trained, controllers)
    checkpoint = resolve_checkpoint(trained.path, checkpoint) or newest_checkpoint(trained)
    proto = get_protocol(protocol or "idt", held_out_patients)
    trials = proto.trials if trials is None else trials
    seed = proto.seed if seed is None else seed
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    overrides = proto.test_env_overrides(trained.env_kwargs)
    clash = sorted(set(env_overrides or {}) & set(PROTOCOL_KEYS))
    if protocol is not None and clash:
        raise ValueError(
            f"env_overrides {clash} contradict protocol {protocol!r}, which sets them itself"
        )
    overrides.update(env_overrides or {})
    name = name or protocol or ("custom" if env_overrides else "idt")
    dest = check_writable(Path(out) if out is not None else trained.path, name)

    settings = acting_settings(trained, safety_filter)
    envs = min(trials, envs or DEFAULT_ENVS)
    episodes = run_controllers(
        trained, trials, envs, seed, device, overrides, controllers, checkpoint=checkpoint,
        safety_filter=safety_filter, progress=progress,
    )  # fmt: skip
    results = {
        c: {
            k: (float(t.mean()), float(t.std()) if trials > 1 else 0.0)
            for k, t in ((k, torch.from_numpy(v)) for k, v in ep["metrics"].items())
        }
        for c, ep in episodes.items()
    }
    spread = {c: distribution(trained.task, ep["metrics"]) for c, ep in episodes.items()}
    run_info = _Evaluation(trained, name, seed, trials, envs, checkpoint, overrides, settings)
    _write_evaluation(dest, run_info, episodes, results, spread, plot)
    return results


@dataclass(frozen=True)
class _Evaluation:
    """What an evaluation ran: the run, its name, seed, trials, envs, checkpoint, env
    overrides and the algorithm's test-time settings."""

    trained: TrainedRun
    name: str
    seed: int
    trials: int
    envs: int
    checkpoint: Path
    overrides: dict[str, Any]
    settings: dict[str, Any]

    def settings_entry(self) -> dict[str, Any]:
        """{their name: the settings} for the files (empty where the algorithm has none)."""
        if not self.settings:
            return {}
        return {_acting(self.trained).settings.name: self.settings}


def _write_evaluation(dest: Path, e: _Evaluation, episodes, results, spread, plot: bool) -> None:
    """The episode log, the trajectory figure (``plot``) and the table of evaluation ``e``."""
    from sonogym.envs.identity import identity
    from sonogym.envs.registry import get_task
    from sonogym.evaluation.episodes import load_log, log_path, plot_trajectories, save_log

    trained = e.trained
    track = get_task(trained.task).track
    test_env = trained.evaluation_env_kwargs(e.overrides)
    made_with = {
        "identity": identity(trained.task, test_env),  # what the episodes ran on
        "train_identity": trained.config.get("identity"),  # what the policy learned on
    }
    meta = {
        "task": trained.task,
        "algo": trained.algo,
        "run": trained.path.resolve().name,
        "train_seed": trained.seed,
        "protocol": e.name,
        "eval_seed": e.seed,
        "trials": e.trials,
        "num_envs": e.envs,  # episode k ran in env k % num_envs: on patient (k % num_envs) % P
        "controllers": list(episodes),
        "checkpoint": e.checkpoint.name,
        **e.settings_entry(),
        "train_env": to_jsonable(trained.env_kwargs),
        "test_env": to_jsonable(test_env),
        **made_with,
        "track_columns": list(track.columns),
        "track_units": list(track.units),
    }
    log = save_log(
        log_path(dest, e.name),
        meta,
        {c: ep["metrics"] for c, ep in episodes.items()},
        {c: ep["track"] for c, ep in episodes.items()},
    )
    if plot:
        plot_trajectories(load_log(log), dest / f"trajectories-{e.name}.png")
    stem = table_stem(e.name)
    table = {
        "task": trained.task,
        "trials": e.trials,
        "seed": e.seed,
        # each env count draws other starts: with trials and seed it fixes the figures
        "num_envs": e.envs,
        "protocol": e.name,
        "checkpoint": e.checkpoint.name,
        **e.settings_entry(),
        "env_overrides": to_jsonable(e.overrides),
        "test_env": to_jsonable(test_env),
        **made_with,
        "results": results,
        "distribution": spread,
    }
    atomic_write_text(dest / f"{stem}.json", json.dumps(table, indent=1))
    atomic_write_text(dest / f"{stem}.md", format_table(results, spread))


def _acting(trained: TrainedRun):
    """How the run's RL algorithm acts (``AlgorithmSpec.acting``); None for an IL run."""
    if trained.kind != "rl":
        return None
    from sonogym.agents.algorithms import get_algorithm

    return get_algorithm(trained.algo).acting


def check_controllers(trained: TrainedRun, controllers: tuple[str, ...]) -> tuple[str, ...]:
    """The controllers to evaluate: ``controllers``, or, where they are the default
    (``CONTROLLERS``), also those the run's algorithm adds, right after "policy"; an unknown
    one is refused, naming the known ones."""
    acting = _acting(trained)
    extra = acting.controllers if acting is not None else ()
    known = ("policy", *extra, "expert", "random")
    unknown = sorted(set(controllers) - set(known))
    if unknown:
        raise ValueError(f"unknown controllers {unknown}; choose from {list(known)}")
    return known if tuple(controllers) == CONTROLLERS else tuple(controllers)


def distribution(task: str, metrics: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Per metric over episodes: the median and, for a metric with a ``tolerance``, the
    fraction of episodes within it (``within``)."""
    from sonogym.envs.registry import get_task

    tol = {m.key: m for m in get_task(task).metrics if m.tolerance is not None}
    out = {}
    for k, v in metrics.items():
        v = np.asarray(v, dtype=np.float64)
        d = {"median": float(np.median(v))}
        if k in tol:
            m = tol[k]
            ok = v <= m.tolerance if m.better == "lower" else v >= m.tolerance
            d["within"] = float(ok.mean())
            d["tolerance"] = m.tolerance
        out[k] = d
    return out


def check_writable(folder: Path, name: str) -> Path:
    """``folder`` after checking that the evaluation's files can be written there and in its
    ``episodes/`` (``sonogym.outputs.check_folder``), so that a read-only run folder or a file
    given as the folder is refused before the episodes run, not after. Creates nothing: the
    folders are made when the files are written."""
    from sonogym.evaluation.episodes import log_path
    from sonogym.outputs import check_folder

    fix = "give --out FOLDER, a folder you can write to, for the table, episode log and figure"
    for where in (folder, log_path(folder, name).parent):
        check_folder(where, "cannot write the evaluation into", fix)
    return folder


def acting_settings(trained: TrainedRun, given: dict[str, Any] | None) -> dict[str, Any]:
    """The test-time settings a run is evaluated with (``evaluate_run``'s ``safety_filter``):
    its algorithm's ``Acting.settings`` resolved with ``given`` (None values: the run's); {}
    for a run whose algorithm takes none, which refuses any given, naming the algorithms that
    take them."""
    given = {k: v for k, v in (given or {}).items() if v is not None}
    acting = _acting(trained)
    hook = acting.settings if acting is not None else None
    if hook is None:
        if given:
            from sonogym.agents.algorithms import algorithm_names, get_algorithm

            takers = [a for a in algorithm_names() if get_algorithm(a).acting.settings]
            raise ValueError(
                f"safety filter settings {sorted(given)} apply to {', '.join(takers)} runs; "
                f"{trained.path} is a {trained.algo} run"
            )
        return {}
    return hook.resolve(trained.config, given)


def controller_policy(
    name: str, env, trained: TrainedRun, seed: int, device: str = "cpu", checkpoint=None,
    safety_filter: dict[str, Any] | None = None,
):  # fmt: skip
    """The ``Policy`` of controller ``name`` in ``env``: the run's trained policy (its
    ``checkpoint``, default the newest readable) as its algorithm acts (a ``ppo-sf`` run's
    through its safety filter, with ``safety_filter``'s mode / threshold if given) or as one of
    the controllers its algorithm adds (``unfiltered``: without the filter), the task's expert
    (or heuristic), or uniform random actions from ``seed``."""
    acting = _acting(trained)
    if name == "policy" or (acting is not None and name in acting.controllers):
        if trained.kind != "rl":
            return run_policy(trained, env, checkpoint, device)
        settings = acting_settings(trained, safety_filter)
        return run_policy(trained, env, checkpoint, device, controller=name, settings=settings)
    if name == "expert":
        from sonogym.envs.policy import ExpertPolicy
        from sonogym.envs.registry import get_task

        return ExpertPolicy(env, get_task(trained.task).expert)
    if name == "random":
        from sonogym.envs.policy import RandomPolicy

        return RandomPolicy(env, seed)
    raise ValueError(f"unknown controller {name!r}; choose from {list(CONTROLLERS)}")


def run_controllers(
    run: str | Path | TrainedRun,
    trials: int,
    envs: int | None = None,
    seed: int = 1000,
    device: str = "cpu",
    env_overrides: dict[str, Any] | None = None,
    controllers: tuple[str, ...] = CONTROLLERS,
    checkpoint: str | Path | None = None,
    safety_filter: dict[str, Any] | None = None,
    progress: bool = False,
) -> dict[str, dict[str, Any]]:
    """Run ``trials`` episodes per controller in the run's env (with ``env_overrides``), all
    from the same seeded starts: {controller: {"metrics": {metric: (trials,) array},
    "track": (trials, T + 1, D) array}} (see ``episodes.run_episodes``). Nothing is written.
    ``progress``: show the env's patients loading and each controller's episodes on stderr
    (``sonogym.progress``)."""
    from sonogym.envs.registry import make_vec
    from sonogym.evaluation.episodes import episode_steps, run_episodes
    from sonogym.progress import progress_bar

    trained = run if isinstance(run, TrainedRun) else load_run(run)
    env_kwargs = {**trained.evaluation_env_kwargs(env_overrides), "device": device}
    with showing_patients(trained.task, env_kwargs, progress):
        env = make_vec(trained.task, min(trials, envs or DEFAULT_ENVS), **env_kwargs)
    out = {}
    for name in controllers:
        policy = controller_policy(name, env, trained, seed, device, checkpoint, safety_filter)
        bar = progress_bar(episode_steps(env, trials), f"{name} ({trials} episodes)",
                           unit="step", enabled=progress)  # fmt: skip
        out[name] = run_episodes(env, policy, trials, seed, trained.task, bar)
        bar.close()
    env.close()
    return out


@contextlib.contextmanager
def showing_patients(task: str, env_kwargs: dict[str, Any], enabled: bool = True) -> Iterator[None]:
    """Around an env's build: a line naming how many patients it loads, then a progress
    display through them on stderr (building a phantom the first time takes seconds; after that
    it is read from the cache)."""
    from sonogym.envs.base import make_config
    from sonogym.envs.patients import patient_progress
    from sonogym.envs.registry import get_task
    from sonogym.progress import announce, progress_bar

    if not enabled:
        yield
        return
    patients = make_config(get_task(task).config_cls, env_kwargs).patients
    n = len(patients) if isinstance(patients, list | tuple) else 1
    announce(f"building the {task} env: {n} patient{'s' if n != 1 else ''} to load")
    bar = progress_bar(n, f"{task} env: patients", unit="patient")
    with patient_progress(lambda spec: bar.update(1)):
        yield
    bar.close()


def format_table(
    results: dict[str, dict[str, tuple[float, float]]],
    spread: dict[str, dict[str, dict[str, float]]] | None = None,
) -> str:
    """Markdown table: one row per controller, mean ± std per metric; with ``spread``
    (``distribution``) also the median and the share of episodes within a metric's tolerance."""
    metrics = sorted({k for r in results.values() for k in r})
    lines = ["| controller | " + " | ".join(metrics) + " |", "|---" * (len(metrics) + 1) + "|"]
    for name, r in results.items():
        cells = []
        for k in metrics:
            if k not in r:
                cells.append("-")
                continue
            cell = f"{r[k][0]:.3f} ± {r[k][1]:.3f}"
            d = (spread or {}).get(name, {}).get(k)
            if d is not None:
                cell += f" (median {d['median']:.3f}"
                if "within" in d:
                    cell += f"; {100 * d['within']:.0f} % within {d['tolerance']:g}"
                cell += ")"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
