"""``sonogym report``: the paper's tables and figures for one task, from finished runs.

Numbers come only from the runs' saved episode logs (``<run>/episodes/<protocol>.npz``, written
by ``sonogym eval``; see ``sonogym.evaluation.episodes``) and, for the learning curves, from
their TensorBoard event files; rerunning the report on the same files gives the same tables.

Pooling: a method's cell pools every episode of every run (seed) of that algorithm under one
protocol and simulator group; mean ± std (sample std, ddof = 1) over episodes. The expert and
random controllers do not depend on the run, so their episodes are counted once per distinct
test env and eval seed.

Outputs in ``out``: ``report.md`` (every table and figure, each with the runs and seeds it came
from and the paper's values where the paper prints numbers), ``metrics.csv`` (every cell, long
format), and per task:

* surgery: ``table1.md`` / ``table1.csv``, the paper's Table 1 (side, insertion, rotation
  error, safe ratio; IDT and ODT columns; rows MB / LB x PPO, PPO + SF, other algorithms, IL
  when present, and our expert for reference); ODT is ``odt-patient`` for MB runs and
  ``odt-sim`` for LB runs;
* navigation, reconstruction: ``bars.png`` (the paper's bar chart, error bars = std);
* reconstruction: ``trajectories.png`` (learned vs heuristic probe path, one episode);
* all: ``curves-<task>-episode_return.png`` / ``.csv`` (learning curves over seeds with the
  expert's return as a reference line).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sonogym.envs.identity import IDENTITY_FILE, check_one_identity, stamp
from sonogym.envs.registry import get_task
from sonogym.envs.spec import Metric
from sonogym.evaluation.curves import (
    algo_label,
    discover_runs,
    expert_label,
    plot_curves,
    run_config,
)
from sonogym.evaluation.episodes import EpisodeLog, run_logs
from sonogym.evaluation.protocols import simulator_group
from sonogym.runs import atomic_write_json, atomic_write_text

RETURN = Metric("return", "return", "", better="higher")


def task_metrics(task: str) -> tuple[Metric, ...]:
    """A task's reported metrics in the paper's order, names and units (task registry)."""
    return get_task(task).metrics


#: The paper's Table 1 (surgery, mean over 100 trials): {(sim, algo): {(metric, column): v}}.
PAPER_TABLE1: dict[tuple[str, str], dict[tuple[str, str], float]] = {
    (sim, algo): {
        (m, col): v
        for m, pair in zip(
            ("side_error_mm", "insertion_error_mm", "rotation_error_deg", "safe_ratio"),
            zip(vals[::2], vals[1::2], strict=True),
            strict=True,
        )
        for col, v in zip(("IDT", "ODT"), pair, strict=True)
    }
    for (sim, algo), vals in {
        ("MB", "PPO"): (2.32, 5.66, 16.0, 20.5, 5.11, 4.54, 99.9, 88.3),
        ("MB", "PPO + SF"): (2.17, 8.94, 13.9, 27.3, 5.36, 4.55, 100.0, 89.8),
        ("MB", "ACT"): (5.38, 18.4, 2.92, 14.5, 0.62, 5.98, 65.9, 65.3),
        ("LB", "PPO"): (5.42, 6.41, 12.3, 26.9, 3.7, 3.76, 93.1, 93.1),
        ("LB", "PPO + SF"): (5.07, 4.56, 11.9, 27.2, 3.93, 3.59, 95.3, 96.0),
        ("LB", "ACT"): (5.34, 6.26, 1.62, 1.72, 1.01, 1.81, 86.0, 80.3),
    }.items()
}
#: The paper's appendix table "new patient" (surgery, LB simulation, held-out patient).
PAPER_NEW_PATIENT: dict[str, tuple[str, ...]] = {
    "PPO": ("27.3 ± 36.4", "12.1 ± 8.77", "8.28 ± 7.33", "52.86"),
    "PPO + SF": ("17.6 ± 54.2", "11.2 ± 7.48", "8.02 ± 7.12", "60.08"),
    "ACT": ("20.7 ± 15.6", "15.4 ± 3.92", "7.64 ± 2.85", "72.06"),
}
#: Method order in tables and charts (others follow alphabetically).
METHOD_ORDER = (
    "PPO",
    "PPO + SF",
    "PPO + SF, filter off",
    "PPO-Lag",
    "A2C",
    "ACT",
    "DP",
    "expert",
    "heuristic",
)


@dataclass(frozen=True)
class Cell:
    """One pooled result: simulator group, protocol, method, metric; episodes and sources."""

    sim: str
    protocol: str
    method: str
    metric: Metric
    values: np.ndarray  # per episode, in the metric's unit
    runs: tuple[str, ...]
    seeds: tuple[int, ...]

    @property
    def mean(self) -> float:
        return float(self.values.mean())

    @property
    def std(self) -> float:
        return float(self.values.std(ddof=1)) if len(self.values) > 1 else 0.0


def _method(controller: str, meta: dict) -> str | None:
    # a policy that saw the privileged state, not the paper's observation, is named so
    state = " (state)" if meta.get("train_env", {}).get("obs_mode") == "state" else ""
    if controller == "policy":
        return algo_label(meta["algo"]) + state
    if controller == "unfiltered":  # a ppo-sf run's policy without its filter
        return f"{algo_label(meta['algo'])}{state}, filter off"
    if controller == "expert":
        return expert_label(meta["task"])
    return "random" if controller == "random" else None


def collect_cells(task: str, logs: list[tuple[Path, EpisodeLog]]) -> list[Cell]:
    """Pool every log's episodes into cells (see the module doc), sorted."""
    pools: dict[tuple[str, str, str, str], dict] = {}
    seen_fixed: set[tuple] = set()
    for run, log in logs:
        meta = log.meta
        sim = simulator_group(meta["test_env"].get("simulator"))
        if meta["protocol"] == "odt-sim":
            sim = "LB"
        for controller, metrics in sorted(log.metrics.items()):
            method = _method(controller, meta)
            if method is None:
                continue
            if controller not in ("policy", "unfiltered"):  # run-independent: count once
                key = (controller, json.dumps(meta["test_env"], sort_keys=True),
                       meta["eval_seed"], meta["trials"], meta["protocol"])  # fmt: skip
                if key in seen_fixed:
                    continue
                seen_fixed.add(key)
            for m in (*task_metrics(task), RETURN):
                if m.key not in metrics:
                    continue
                p = pools.setdefault(
                    (sim, meta["protocol"], method, m.key), {"v": [], "runs": [], "seeds": []}
                )
                p["v"].append(np.asarray(metrics[m.key], np.float64) * m.scale)
                p["runs"].append(run.name)
                p["seeds"].append(int(meta["train_seed"]))
    by_key = {m.key: m for m in (*task_metrics(task), RETURN)}
    cells = [
        Cell(
            sim,
            proto,
            method,
            by_key[k],
            np.concatenate(p["v"]),
            tuple(p["runs"]),
            tuple(p["seeds"]),
        )  # fmt: skip
        for (sim, proto, method, k), p in pools.items()
    ]
    return sorted(cells, key=lambda c: (c.sim, c.protocol, _order(c.method), c.metric.key))


def _order(method: str) -> tuple[int, str]:
    base = method.replace(" (state)", "")  # beside the method it is a variant of
    return (
        (METHOD_ORDER.index(base), method) if base in METHOD_ORDER else (len(METHOD_ORDER), method)
    )


def _fmt(x: float) -> str:
    return f"{x:.3g}" if abs(x) < 1000 else f"{x:.0f}"


def _sources(cells: list[Cell]) -> str:
    pairs = sorted({(r, s) for c in cells for r, s in zip(c.runs, c.seeds, strict=True)})
    return ", ".join(f"{r} (seed {s})" for r, s in pairs) or "none"


# ----------------------------------------------------------------------------- tables


def metrics_csv(cells: list[Cell]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["sim", "protocol", "method", "metric", "unit", "mean", "std", "n", "runs", "seeds"])
    for c in cells:
        w.writerow(
            [c.sim, c.protocol, c.method, c.metric.key, c.metric.unit, f"{c.mean:.6g}",
             f"{c.std:.6g}", len(c.values), " ".join(c.runs), " ".join(map(str, c.seeds))]
        )  # fmt: skip
    return buf.getvalue()


def table1_columns() -> list[tuple[Metric, str]]:
    """Table 1's value columns: (metric, IDT | ODT), in the paper's order."""
    return [(m, col) for m in task_metrics("surgery") for col in ("IDT", "ODT")]


def table1(cells: list[Cell]) -> tuple[str, str, list[Cell]]:
    """(markdown, csv, cells used) of the paper's Table 1 from surgery cells."""
    idx: dict[tuple[str, str, str, str], Cell] = {}
    for c in cells:
        col = "IDT" if c.protocol == "idt" else None
        if (c.sim, c.protocol) in (("MB", "odt-patient"), ("LB", "odt-sim")):
            col = "ODT"
        if col is not None:
            idx[(c.sim, c.method, c.metric.key, col)] = c
    rows = sorted(
        {(s, m) for s, m, _, _ in idx if m != "random"}, key=lambda r: (r[0] != "MB", _order(r[1]))
    )
    cols = table1_columns()
    head = ["US sim", "Algos"] + [f"{m.label} [{m.unit}] {col}" for m, col in cols]
    md = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        ["us_sim", "algos"]
        + [f"{m.key}_{col}_{s}" for m, col in cols for s in ("mean", "std", "n")]
    )
    used = []
    for sim, method in rows:
        cells_md, cells_csv = [], []
        for m, col in cols:
            c = idx.get((sim, method, m.key, col))
            if c is None:
                cells_md.append("–")
                cells_csv += ["", "", ""]
            else:
                used.append(c)
                cells_md.append(f"{_fmt(c.mean)} ± {_fmt(c.std)}")
                cells_csv += [f"{c.mean:.6g}", f"{c.std:.6g}", len(c.values)]
        md.append(f"| {sim} | {method} | " + " | ".join(cells_md) + " |")
        w.writerow([sim, method, *cells_csv])
    if not rows:
        md.append("| – | (no surgery episode logs) |" + " – |" * len(cols))
    return "\n".join(md) + "\n", buf.getvalue(), used


def new_patient_table(cells: list[Cell]) -> tuple[str, list[Cell]] | None:
    """(markdown, cells) of the appendix's "new patient" table: LB runs under ``odt-patient``;
    None when there are none."""
    use = [
        c for c in cells if (c.sim, c.protocol) == ("LB", "odt-patient") and c.method != "random"
    ]
    if not use:
        return None
    idx = {(c.method, c.metric.key): c for c in use}
    mets = task_metrics("surgery")
    md = ["| Algos | " + " | ".join(f"{m.label} [{m.unit}]" for m in mets) + " |",
          "|" + "---|" * (len(mets) + 1)]  # fmt: skip
    for method in sorted({c.method for c in use}, key=_order):
        row = [idx.get((method, m.key)) for m in mets]
        vals = ["–" if c is None else f"{_fmt(c.mean)} ± {_fmt(c.std)}" for c in row]
        md.append(f"| {method} | " + " | ".join(vals) + " |")
    return "\n".join(md) + "\n", use


def paper_table1_md() -> str:
    cols = table1_columns()
    head = ["US sim", "Algos"] + [f"{m.label} [{m.unit}] {col}" for m, col in cols]
    md = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (sim, algo), vals in PAPER_TABLE1.items():
        md.append(
            f"| {sim} | {algo} | " + " | ".join(f"{vals[(m.key, c)]:g}" for m, c in cols) + " |"
        )
    return "\n".join(md) + "\n"


# ----------------------------------------------------------------------------- figures


def _group_name(sim: str, protocol: str) -> str:
    if protocol == "idt":
        return sim
    if protocol == "odt-sim":
        return "LB_ODT"
    return f"{sim}_{protocol.upper().replace('-', '_')}"


def bar_chart(task: str, cells: list[Cell], path: Path) -> tuple[Path, list[Cell]] | None:
    """The paper's bar chart: one panel per metric, groups = simulator/protocol (MB, LB,
    LB_ODT, ...), bars = methods, error bars = std over episodes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    use = [c for c in cells if c.method != "random" and c.metric.key != "return"]
    if not use:
        return None
    groups = sorted(
        {(c.sim, c.protocol) for c in use}, key=lambda g: (g[1] != "idt", g[0] != "MB", g)
    )
    methods = sorted({c.method for c in use}, key=_order)
    idx = {(c.sim, c.protocol, c.method, c.metric.key): c for c in use}
    mets = [m for m in task_metrics(task) if any(c.metric.key == m.key for c in use)]
    fig, axes = plt.subplots(1, len(mets), figsize=(3.4 * len(mets) + 1, 3.6), squeeze=False)
    width = 0.8 / len(methods)
    for ax, m in zip(axes[0], mets, strict=True):
        for j, method in enumerate(methods):
            xs, ys, es = [], [], []
            for i, (sim, proto) in enumerate(groups):
                c = idx.get((sim, proto, method, m.key))
                if c is not None:
                    xs.append(i + (j - (len(methods) - 1) / 2) * width)
                    ys.append(c.mean)
                    es.append(c.std)
            ax.bar(xs, ys, width, yerr=es, capsize=3, label=method, color=plt.cm.tab10(j % 10))
        ax.set_xticks(
            range(len(groups)), [_group_name(*g).replace("_", "\n", 1) for g in groups], fontsize=8
        )
        ax.set_ylabel(f"{m.label} [{m.unit}]")
    axes[0][0].legend(fontsize=7)
    n = sorted({len(c.values) for c in use})
    fig.suptitle(
        f"{task}: mean ± std over {'/'.join(map(str, n))} episodes; runs: {_sources(use)}",
        fontsize=6,
        wrap=True,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return path, use


def reconstruction_trajectories(
    logs: list[tuple[Path, EpisodeLog]], path: Path, episode: int = 0
) -> tuple[Path, str] | None:
    """Learned vs heuristic probe path (x, z relative to the vertebra, mm) of one in-domain
    episode of the first reconstruction run (by name), like the paper's figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cands = [(r, lg) for r, lg in logs if lg.meta["protocol"] == "idt"
             and {"policy", "expert"} <= set(lg.tracks)]  # fmt: skip
    if not cands:
        return None
    run, log = min(cands, key=lambda x: x[0].name)
    cols = log.meta["track_columns"]
    i, j = cols.index("x"), cols.index("z")
    fig, axes = plt.subplots(1, 2, figsize=(7, 3.6))
    for ax, c, name in zip(axes, ("policy", "expert"), ("learned", "heuristic"), strict=True):
        p = log.tracks[c][episode]
        cov = log.metrics[c]["coverage"][episode] * 100
        ax.plot(p[:, i], p[:, j], "-", lw=1.2)
        ax.plot(p[0, i], p[0, j], "go", ms=5, label="start")
        ax.plot(p[-1, i], p[-1, j], "rx", ms=6, label="end")
        ax.plot(0, 0, "k+", ms=10, label="vertebra centre")
        ax.set_title(f"{name} ({algo_label(log.meta['algo']) if c == 'policy' else 'raster'}), "
                     f"coverage {cov:.1f} %", fontsize=9)  # fmt: skip
        ax.set_xlabel("x [mm]")
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].set_ylabel("z [mm]")
    axes[0].legend(fontsize=7)
    src = (f"run {run.name} (seed {log.meta['train_seed']}), protocol idt, episode {episode} of "
           f"{log.meta['trials']}, eval seed {log.meta['eval_seed']}")  # fmt: skip
    fig.suptitle(f"reconstruction trajectories: {src}", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return path, src


# ----------------------------------------------------------------------------- report


def results_identity(runs: list[Path], logs: list[tuple[Path, EpisodeLog]]) -> dict:
    """The one benchmark identity of ``runs`` (as trained) and their episode ``logs`` (as
    evaluated); ``IdentityMismatch`` names the run or evaluation that differs, and in what."""
    named = {f"{r.name} (training)": run_config(r).get("identity") for r in runs}
    for r, lg in logs:
        named[f"{r.name} (evaluation {lg.meta.get('protocol')})"] = lg.meta.get("identity")
    return check_one_identity(named)


def build_report(
    task: str,
    runs: list[str | Path],
    out: str | Path,
    curves: bool = True,
    expert_episodes: int = 4,
    command: str | None = None,
) -> Path:
    """Write the task's tables and figures (module doc) to ``out``; returns ``out/report.md``."""
    get_task(task)  # an unknown task names the known ones
    out = Path(out)
    all_runs = discover_runs(list(runs))
    task_runs = [r for r in all_runs if run_config(r)["task"] == task]
    if not task_runs:
        raise FileNotFoundError(f"no {task} runs among {[str(r) for r in all_runs]}")
    logs = [(r, lg) for r in task_runs for lg in run_logs(r)]
    made_with = results_identity(task_runs, logs)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / IDENTITY_FILE, made_with)
    cells = collect_cells(task, logs)
    cmd = command or f"sonogym report --task {task} --runs " + " ".join(str(r) for r in runs)
    md = [f"# SonoGym report: {task}\n", f"Made by: `{cmd}`\n", f"{stamp(made_with)}\n"]
    names = [f"{r.name} ({run_config(r)['algo']}, seed {run_config(r)['seed']})" for r in task_runs]
    md.append("Runs: " + ", ".join(names) + "\n")
    if not logs:
        md.append("No episode logs: run `sonogym eval --run <run> --protocol idt` first.\n")
    atomic_write_text(out / "metrics.csv", metrics_csv(cells))
    md.append("Every number: [metrics.csv](metrics.csv) (mean, std over episodes, n, runs, "
              "seeds).\n")  # fmt: skip

    if task == "surgery":
        t_md, t_csv, used = table1(cells)
        atomic_write_text(out / "table1.md", f"{stamp(made_with)}\n\n{t_md}")
        atomic_write_text(out / "table1.csv", t_csv)
        md += [
            "## Table 1: surgery (mean ± std over episodes)\n",
            "ODT = held-out patient (`odt-patient`) for MB rows, held-out learned net "
            "(`odt-sim`) for LB rows.\n",
            t_md,
            f"Source runs: {_sources(used)}\n",
            "Paper, Table 1 (mean over 100 trials; the paper marks safe ratio with a ↓, "
            "higher is safer):\n",
            paper_table1_md(),
        ]
        extra = new_patient_table(cells)
        if extra is not None:
            mets = task_metrics("surgery")
            paper = ["| Algos | " + " | ".join(f"{m.label} [{m.unit}]" for m in mets) + " |",
                     "|" + "---|" * (len(mets) + 1)]  # fmt: skip
            paper += [f"| {a} | " + " | ".join(v) + " |" for a, v in PAPER_NEW_PATIENT.items()]
            md += [
                "## New patient, learned simulation (appendix table)\n",
                extra[0],
                f"Source runs: {_sources(extra[1])}\n",
                "Paper:\n",
                "\n".join(paper) + "\n",
            ]
    else:
        res = bar_chart(task, cells, out / "bars.png")
        if res is not None:
            md += [f"## {task}: metrics (bar chart)\n", "![bars](bars.png)\n",
                   f"Source runs: {_sources(res[1])}\n"]  # fmt: skip
        if task == "reconstruction":
            tr = reconstruction_trajectories(logs, out / "trajectories.png")
            if tr is not None:
                md += ["## Learned vs heuristic trajectory\n",
                       "![trajectories](trajectories.png)\n", f"Source: {tr[1]}\n"]  # fmt: skip
    if curves:
        pngs = plot_curves(task_runs, out, expert_episodes=expert_episodes, stem="curves")
        for p in pngs:
            md.append(f"## Learning curves\n\n![{p.stem}]({p.name})\n")
        if pngs:
            md.append("Runs and seeds: [curves.md](curves.md)\n")
    atomic_write_text(out / "report.md", "\n".join(md))
    return out / "report.md"
