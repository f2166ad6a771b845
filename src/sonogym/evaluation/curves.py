"""Learning curves over seeds from the runs' TensorBoard event files (``sonogym plot``).

Runs are grouped by (task, algo); each group's curve is the mean ± 1 sigma across its runs
(seeds) of a scalar (default ``Episode / return``, the env's undiscounted episode return),
against env steps summed over all envs (skrl's per-env timestep x the run's ``num_envs``),
interpolated onto a common grid over the steps every run reached. Like the paper's learning-curve
figure, the expert's (reconstruction: the heuristic's) mean episode value is drawn as a
horizontal reference line: read from the run's episode logs or ``eval.json`` when present,
else measured by running the expert in the run's env for a few seeded episodes.
"""

from __future__ import annotations

import csv
import io
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sonogym.envs.identity import IDENTITY_FILE, check_one_identity, stamp
from sonogym.evaluation.trained import load_run
from sonogym.runs import atomic_write_json, atomic_write_text

DEFAULT_METRIC = "Episode / return"


def algo_label(algo: str) -> str:
    """A run's algorithm as plots and reports name it: the label its registry gives (RL:
    ``sonogym.agents.algorithms``; imitation: ``sonogym.imitation.policies.registry``), else
    the name itself (a run of an algorithm no longer registered)."""
    from sonogym.agents.algorithms import algorithm_names, get_algorithm
    from sonogym.imitation.policies.registry import policy_for_algo

    spec = policy_for_algo(algo)
    if spec is not None:
        return spec.label
    return get_algorithm(algo).label if algo in algorithm_names() else algo


def curve_label(c: Curve) -> str:
    """A curve's legend name: the algorithm, "(LB)" for learned-simulator runs."""
    return algo_label(c.algo) + (" (LB)" if c.sim == "LB" else "")


def expert_label(task: str) -> str:
    """What the task's privileged controller is called ("expert" or "heuristic")."""
    from sonogym.envs.registry import get_task

    return get_task(task).expert_label


# ----------------------------------------------------------------------------- runs


def discover_runs(paths: list[str | Path]) -> list[Path]:
    """Run folders (holding ``config.json``) named by ``paths``: a run folder itself, or every
    run folder below a folder (two levels deep). Sorted, without duplicates."""
    found: set[Path] = set()
    for p in map(Path, paths):
        if (p / "config.json").is_file():
            found.add(p)
            continue
        if not p.is_dir():
            raise FileNotFoundError(f"{p}: no such run folder")
        below = [c.parent for c in (*p.glob("*/config.json"), *p.glob("*/*/config.json"))]
        if not below:
            raise FileNotFoundError(f"{p}: neither a run folder (config.json) nor holds any")
        found.update(below)
    return sorted(found)


def run_config(run: str | Path) -> dict:
    """A run's whole config.json (RL or IL)."""
    return load_run(run).config


def group_runs(runs: list[Path]) -> dict[tuple[str, str, str], list[Path]]:
    """{(task, algo, simulator group "MB" | "LB"): [runs]}, runs sorted by seed then path."""
    from sonogym.evaluation.protocols import simulator_group

    groups: dict[tuple[str, str, str], list[Path]] = {}
    for r in runs:
        c = load_run(r)
        sim = simulator_group(c.env_kwargs.get("simulator"))
        groups.setdefault((c.task, c.algo, sim), []).append(r)
    return {
        k: sorted(v, key=lambda r: (load_run(r).seed, str(r))) for k, v in sorted(groups.items())
    }


# ----------------------------------------------------------------------------- scalars


def read_scalar(run: str | Path, tag: str) -> tuple[np.ndarray, np.ndarray]:
    """(env steps over all envs, values) of one TensorBoard scalar of a run (every event file
    in the run folder, resumed segments included; the last value per step wins)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = Path(run)
    num_envs = load_run(run).num_envs or 1  # IL runs: optimiser steps
    points: dict[int, float] = {}
    for ev in sorted(run.glob("events.out.tfevents.*")):
        acc = EventAccumulator(str(ev), size_guidance={"scalars": 0})
        acc.Reload()
        if tag not in acc.Tags()["scalars"]:
            continue
        for e in acc.Scalars(tag):
            points[int(e.step)] = float(e.value)
    if not points:
        raise KeyError(f"{run}: no TensorBoard scalar {tag!r}")
    steps = np.array(sorted(points), dtype=np.float64)
    return steps * num_envs, np.array([points[int(s)] for s in sorted(points)], np.float64)


@dataclass
class Curve:
    """Mean and std over seeds of one (task, algo) group on a common step grid."""

    task: str
    algo: str
    sim: str  # "MB" | "LB"
    metric: str
    steps: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    runs: list[str] = field(default_factory=list)
    seeds: list[int] = field(default_factory=list)


def curve_over_seeds(runs: list[Path], metric: str = DEFAULT_METRIC, points: int = 200) -> Curve:
    """The group's curve: each run interpolated onto a grid over the steps all runs reached
    (runs without the scalar are left out; KeyError when none has it)."""
    found = []
    for r in runs:
        try:
            found.append((r, read_scalar(r, metric)))
        except KeyError:
            continue
    if not found:
        raise KeyError(f"no run of {[str(r) for r in runs]} has the scalar {metric!r}")
    runs = [r for r, _ in found]
    series = [s for _, s in found]
    lo = max(s[0][0] for s in series)
    hi = min(s[0][-1] for s in series)
    if hi < lo:
        raise ValueError(f"runs {[str(r) for r in runs]} share no step range for {metric!r}")
    if len(series) == 1:
        steps, values = series[0]
        ys = values[None]
    else:
        n = min(points, max(len(s[0]) for s in series))
        steps = np.linspace(lo, hi, max(n, 2)) if hi > lo else np.array([lo])
        ys = np.stack([np.interp(steps, x, y) for x, y in series])
    from sonogym.evaluation.protocols import simulator_group

    cfgs = [load_run(r) for r in runs]
    return Curve(
        task=cfgs[0].task,
        algo=cfgs[0].algo,
        sim=simulator_group(cfgs[0].env_kwargs.get("simulator")),
        metric=metric,
        steps=steps,
        mean=ys.mean(0),
        std=ys.std(0),
        runs=[r.name for r in runs],
        seeds=[c.seed for c in cfgs],
    )


# ----------------------------------------------------------------------------- expert


def _episode_metric(metric: str) -> str | None:
    """The env metric a TensorBoard tag shows (``Episode / <m>``), or None."""
    m = re.fullmatch(r"Episode / (.+)", metric)
    if m:
        return m.group(1)
    if metric.startswith("Reward / Total reward"):
        return "return"
    return None


def expert_reference(
    run: str | Path, metric: str = DEFAULT_METRIC, episodes: int = 4, seed: int = 1000
) -> tuple[float, str] | None:
    """(the expert's mean of ``metric``'s env metric, where it came from) for one run: its
    in-domain episode log, else its ``eval.json``, else ``episodes`` seeded expert episodes in
    the run's env (nothing written). None when the tag is not an episode metric."""
    from sonogym.evaluation.episodes import load_log, log_path

    key = _episode_metric(metric)
    if key is None:
        return None
    run = Path(run)
    log = log_path(run, "idt")
    if log.exists():
        m = load_log(log).metrics.get("expert", {})
        if key in m:
            return float(np.asarray(m[key], np.float64).mean()), f"{log.relative_to(run.parent)}"
    ev = run / "eval.json"
    if ev.exists():
        r = json.loads(ev.read_text()).get("results", {}).get("expert", {})
        if key in r:
            return float(r[key][0]), f"{ev.relative_to(run.parent)}"
    from sonogym.evaluation.rl_eval import run_controllers

    res = run_controllers(run, episodes, seed=seed, controllers=("expert",))["expert"]["metrics"]
    if key not in res:
        return None
    return float(
        np.asarray(res[key], np.float64).mean()
    ), f"{episodes} expert episodes (seed {seed})"


# ----------------------------------------------------------------------------- plot


def _count(n: int, what: str) -> str:
    return f"{n} {what}{'s' if n != 1 else ''}"


def _slug(metric: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", metric.lower()).strip("_")


def plot_curves(
    runs: list[Path],
    out: str | Path,
    metrics: tuple[str, ...] = (DEFAULT_METRIC,),
    expert: bool = True,
    expert_episodes: int = 4,
    stem: str = "curves",
) -> list[Path]:
    """One figure per (task, metric): each algo's mean ± 1 sigma over its seeds, the expert's
    mean as a dashed line. Writes ``<stem>-<task>-<metric>.png`` and ``.csv`` (the plotted
    numbers) and ``<stem>.md`` (which runs and seeds made each figure). Returns the PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    groups = group_runs(runs)
    tasks = sorted({t for t, _, _ in groups})
    # one identity per task's figures, checked before anything is written
    made_with = {
        task: check_one_identity(
            {r.name: run_config(r).get("identity") for (t, _, _), rs in groups.items()
             if t == task for r in rs}
        )
        for task in tasks
    }  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / IDENTITY_FILE, made_with)
    written: list[Path] = []
    md = [f"# Learning curves\n\nmean ± 1σ over seeds; metrics {', '.join(metrics)}"]
    md += [stamp(made_with[task]) for task in tasks]
    for task in tasks:
        for metric in metrics:
            curves = []
            for (t, _, _), rs in groups.items():
                if t != task:
                    continue
                try:
                    curves.append(curve_over_seeds(rs, metric))
                except KeyError:
                    continue
            if not curves:
                continue
            ref = None
            if expert:
                task_runs = [r for (t, _, _), rs in groups.items() if t == task for r in rs]
                refs = [expert_reference(r, metric, expert_episodes) for r in task_runs]
                refs = [x for x in refs if x is not None]
                if refs:
                    ref = (float(np.mean([v for v, _ in refs])), [s for _, s in refs])
            name = f"{stem}-{task}-{_slug(metric)}"
            source = "; ".join(
                f"{curve_label(c)}: "
                + ", ".join(f"{r} (seed {s})" for r, s in zip(c.runs, c.seeds, strict=True))
                for c in curves
            )
            fig, ax = plt.subplots(figsize=(6, 4))
            for c in curves:
                (line,) = ax.plot(
                    c.steps,
                    c.mean,
                    label=f"{curve_label(c)} ({_count(len(c.seeds), 'seed')})",
                )
                ax.fill_between(
                    c.steps, c.mean - c.std, c.mean + c.std, alpha=0.25, color=line.get_color()
                )
            if ref is not None:
                ax.axhline(ref[0], color="red", ls="--", label=expert_label(task))
            ax.set_xlabel("env steps (all envs)")
            ax.set_ylabel(metric)
            ax.set_title(f"{task}: {metric}", fontsize=10)
            ax.legend(fontsize=8)
            fig.text(0.01, 0.005, f"{stamp(made_with[task])}; runs: {source}", fontsize=5,
                     wrap=True)  # fmt: skip
            fig.tight_layout(rect=(0, 0.04, 1, 1))
            png = out / f"{name}.png"
            fig.savefig(png, dpi=100, metadata={"Software": None})
            plt.close(fig)
            atomic_write_text(out / f"{name}.csv", _curves_csv(curves, ref))
            written.append(png)
            md.append(f"## {task}: {metric}\n\n![{name}]({name}.png)\n\nruns: {source}")
            if ref is not None:
                md.append(f"{expert_label(task)} reference {ref[0]:.4g} from: {'; '.join(ref[1])}")
            md.append(f"numbers: [{name}.csv]({name}.csv)")
    atomic_write_text(out / f"{stem}.md", "\n\n".join(md).rstrip() + "\n")
    return written


def _curves_csv(curves: list[Curve], ref: tuple[float, list[str]] | None) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["task", "algo", "sim", "metric", "env_steps", "mean", "std", "seeds", "runs"])
    for c in curves:
        for x, m, s in zip(c.steps, c.mean, c.std, strict=True):
            w.writerow(
                [c.task, c.algo, c.sim, c.metric, f"{x:.0f}", f"{m:.6g}", f"{s:.6g}",
                 " ".join(map(str, c.seeds)), " ".join(c.runs)]
            )  # fmt: skip
    if ref is not None:
        w.writerow(
            [curves[0].task, "expert", "", curves[0].metric, "", f"{ref[0]:.6g}", "", "", ""]
        )
    return buf.getvalue()
