"""``sonogym select``: choose a run's checkpoint on patients kept for selection, never on the
patients that report its figures.

Every checkpoint of the run (or the ones given) is evaluated, policy only, on the selection
patients (for example held-out phantoms that no evaluation reports and real-derived variants
``DIR@N``), from one seed; the checkpoint with the best mean of the chosen metric is selected.
Each checkpoint's evaluation goes to ``<run>/selection/`` (``eval-step-<t>.json`` and its
episode log), the summary to ``<run>/selection.json`` and ``selection.md``.

``sonogym export`` reads ``selection.json``: by default it exports the selected checkpoint, the
model card says how it was chosen, and an evaluation of that checkpoint on a selection patient
is refused (its figure would not be a test).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from sonogym.runs import atomic_write_json, atomic_write_text

SELECTION = "selection.json"
SELECTION_DIR = "selection"


def select_checkpoint(
    run: str | Path,
    patients: Sequence[int | str],
    metric: str | None = None,
    trials: int = 50,
    envs: int | None = None,
    seed: int = 2000,
    checkpoints: Sequence[str | Path] | None = None,
    device: str = "cpu",
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Evaluate ``run``'s checkpoints on ``patients`` and select the best by ``metric``'s mean
    (default: the task's first metric; its ``better`` side decides); ties go to the earlier
    checkpoint. Returns the summary written to ``<run>/selection.json``."""
    from sonogym.envs.registry import get_task
    from sonogym.evaluation.rl_eval import evaluate_run
    from sonogym.evaluation.trained import load_run

    trained = load_run(run)
    task = get_task(trained.task)
    chosen_metric = task.metric(metric) if metric else task.metrics[0]
    if not patients:
        raise ValueError("give the selection patients (--patients): none were given")
    if trials < 1:
        raise ValueError(f"trials must be >= 1, got {trials}")
    folder = trained.folder
    found = (
        [(folder.kind.step_of(p), Path(p)) for p in checkpoints]
        if checkpoints
        else folder.checkpoints()
    )
    if not found:
        raise FileNotFoundError(f"no checkpoints to select from in {trained.path}/checkpoints")
    rows = []
    for step, path in found:
        if not path.is_file():
            raise FileNotFoundError(f"checkpoint {path} not found")
        if path.parent.resolve() != (trained.path / "checkpoints").resolve():
            raise ValueError(
                f"checkpoint {path} is not one of {trained.path}/checkpoints: select among the "
                "run's own checkpoints (the selection names it there)"
            )
        log(f"select: {path.name} on {len(patients)} patients, {trials} episodes")
        results = evaluate_run(
            trained.path, trials=trials, envs=envs, seed=seed, device=device,
            env_overrides={"patients": tuple(patients)}, controllers=("policy",), plot=False,
            checkpoint=path, name=f"step-{step}", out=trained.path / SELECTION_DIR,
        )  # fmt: skip
        policy = results["policy"]
        rows.append({"checkpoint": path.name, "step": step,
                     "results": {k: list(v) for k, v in policy.items()}})  # fmt: skip
    sign = 1.0 if chosen_metric.better == "lower" else -1.0
    best = min(rows, key=lambda r: sign * r["results"][chosen_metric.key][0])
    summary = {
        "task": trained.task,
        "metric": chosen_metric.key,
        "better": chosen_metric.better,
        "patients": [str(p) for p in patients],
        "trials": trials,
        "seed": seed,
        "selected": best["checkpoint"],
        "checkpoints": rows,
    }
    atomic_write_json(trained.path / SELECTION, summary)
    atomic_write_text(trained.path / "selection.md", selection_markdown(summary))
    return summary


def selection_markdown(summary: dict[str, Any]) -> str:
    """The selection as a table, the selected checkpoint marked."""
    keys = list(summary["checkpoints"][0]["results"])
    lines = [
        f"Checkpoint selection on patients {', '.join(summary['patients'])} "
        f"({summary['trials']} episodes each from seed {summary['seed']}; "
        f"{summary['better']} {summary['metric']} is better): **{summary['selected']}**",
        "",
        "| checkpoint | " + " | ".join(keys) + " |",
        "|---" * (len(keys) + 1) + "|",
    ]
    for r in summary["checkpoints"]:
        mark = " (selected)" if r["checkpoint"] == summary["selected"] else ""
        cells = [f"{m:.3f} ± {s:.3f}" for m, s in (r["results"][k] for k in keys)]
        lines.append(f"| {r['checkpoint']}{mark} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


#: ``checkpoint`` value that names the checkpoint ``sonogym select`` chose.
SELECTED = "selected"


def resolve_checkpoint(run: str | Path, checkpoint: str | Path | None) -> Path | None:
    """``checkpoint`` as a path: ``"selected"`` is the run's selected one (``selection.json``;
    an error when the run has none), anything else is returned as given."""
    if checkpoint is None or str(checkpoint) != SELECTED:
        return None if checkpoint is None else Path(checkpoint)
    selection = read_selection(run)
    if selection is None:
        raise FileNotFoundError(
            f"--checkpoint selected: {run} has no {SELECTION}; run sonogym select --run {run} "
            "--patients ... first"
        )
    return Path(run) / "checkpoints" / selection["selected"]


def read_selection(run: str | Path) -> dict[str, Any] | None:
    """A run's ``selection.json`` (None when it has none)."""
    path = Path(run) / SELECTION
    return json.loads(path.read_text()) if path.is_file() else None


def tested_on_selection(selection: dict[str, Any], evaluations: dict[str, dict]) -> list[str]:
    """The evaluations (name -> card entry with ``test_env``) that test on a patient the
    checkpoint was selected on, each with the patients in common."""
    from sonogym.evaluation.cohort import overlap

    out = []
    for name, e in evaluations.items():
        test = e.get("test_env", {}).get("patients") or ()
        test = [test] if isinstance(test, int | str) else test
        common = overlap(selection["patients"], test)
        if common:
            out.append(f"{name} (patients {', '.join(map(str, common))})")
    return out
