"""The record of ``sonogym select`` (``checkpoint_selection.select_checkpoint``): a run's
checkpoint chosen on patients kept for selection, never on the patients that report its
figures.

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
from pathlib import Path
from typing import Any

SELECTION = "selection.json"
SELECTION_DIR = "selection"


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
