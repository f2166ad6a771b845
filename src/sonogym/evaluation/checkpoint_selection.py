"""``sonogym select``: evaluate a run's checkpoints on selection patients and record the best
(``sonogym.evaluation.selection`` reads and checks the record)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from sonogym.evaluation.selection import SELECTION, SELECTION_DIR, selection_markdown
from sonogym.runs import atomic_write_json, atomic_write_text


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
