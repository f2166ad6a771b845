"""Trained policies that ship with sonogym, evaluated exactly like a run of your own.

Each lives in the package's ``pretrained/<name>/`` folder:

* ``config.json``: the training run's own (``sonogym train`` wrote it), so the policy is rebuilt
  as that run's would be;
* ``policy.safetensors``: the acting weights of the chosen checkpoint (``safetensors``: tensors
  only, nothing is unpickled);
* ``model_card.json`` / ``model_card.md``: what it was trained on, for how long, at what CPU
  cost, and how it scored.

``sonogym eval --pretrained NAME --out DIR`` evaluates one (the same table, ``eval*.json`` and
episode log as ``sonogym eval --run``, written to ``DIR``); ``--pretrained list`` lists them.
``export_pretrained`` (``sonogym export``) makes one from a run folder.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sonogym.evaluation.selection import read_selection, resolve_checkpoint, tested_on_selection
from sonogym.runs import (
    SHIPPED_WEIGHTS,
    RunFolder,
    atomic_write_json,
    atomic_write_text,
    read_json,
)

#: Where shipped policies live (inside the installed package).
PRETRAINED_DIR = Path(__file__).resolve().parents[1] / "pretrained"
WEIGHTS = SHIPPED_WEIGHTS
CARD = "model_card.json"


def available(root: str | Path | None = None) -> list[str]:
    """Names of the policies under ``root`` (default ``PRETRAINED_DIR``: folders holding a
    config and weights)."""
    root = Path(PRETRAINED_DIR if root is None else root)
    if not root.is_dir():
        return []
    return sorted(
        p.name for p in root.iterdir() if (p / "config.json").is_file() and (p / WEIGHTS).is_file()
    )


def pretrained_dir(name: str, root: str | Path | None = None) -> Path:
    """The folder of shipped policy ``name``; an unknown name lists the known ones."""
    known = available(root)
    if name not in known:
        raise ValueError(
            f"no pretrained policy {name!r}; sonogym ships {known or 'none'} "
            "(sonogym eval --pretrained list)"
        )
    return Path(PRETRAINED_DIR if root is None else root) / name


def weights(name: str, root: str | Path | None = None) -> Path:
    """The weights file of shipped policy ``name`` (the checkpoint evaluation loads)."""
    return pretrained_dir(name, root) / WEIGHTS


def read_card(name: str, root: str | Path | None = None) -> dict[str, Any]:
    """The model card of shipped policy ``name`` ({} if it has none)."""
    path = pretrained_dir(name, root) / CARD
    return read_json(path, "pretrained policy") if path.is_file() else {}


def listing(root: str | Path | None = None) -> str:
    """One line per shipped policy: name, task, algorithm, observation and headline figures."""
    lines = []
    for name in available(root):
        card = read_card(name, root)
        head = card.get("headline", "")
        src = card.get("init_from")
        tuned = f" (fine-tuned from {src['run']}/{src['checkpoint']})" if src else ""
        lines.append(
            f"{name}: {card.get('task', '?')} {card.get('algo', '?')}, observation "
            f"{card.get('obs_mode') or 'default'}, {card.get('steps_total', '?')} env steps"
            f"{tuned}, {card.get('cpu_minutes', '?')} CPU min in all"
            + (f"; {head}" if head else "")
        )
    return "\n".join(lines) if lines else "no pretrained policies ship with this sonogym"


#: The files ``export_pretrained`` writes into a policy's folder: ``force`` replaces these and
#: nothing else.
EXPORTED = ("config.json", WEIGHTS, CARD, "model_card.md")


def export_pretrained(
    run: str | Path,
    name: str,
    root: str | Path,
    checkpoint: str | Path | None = None,
    notes: str = "",
    force: bool = False,
    log: Callable[[str], None] = lambda message: None,
    warn: Callable[[str], None] = warnings.warn,
) -> Path:
    """Write run ``run``'s policy as shipped policy ``name`` under ``root`` (the package's own
    folder is ``PRETRAINED_DIR``; it is never a default): its config, the acting weights of
    ``checkpoint`` (default: the newest readable) and a model card from the run's config, its
    ``checkpoints/times.json`` and the evaluations in its folder (``eval*.json`` of that
    checkpoint), saying how far the run got and which evaluations there are.

    The run, the checkpoint and the destination are checked before anything is written. A
    folder ``root/name`` that already holds a policy is refused unless ``force``, which
    replaces only the files export writes (``EXPORTED``); any other file there is kept and
    named through ``log``. ``warn`` is told when the checkpoint falls short of the run's
    planned steps or has no evaluation. A failed export leaves nothing it made."""
    import re

    from sonogym.agents.checkpoint import (
        RL_RUN,
        acting_modules,
        export_acting_weights,
        run_config,
    )
    from sonogym.agents.train import read_times
    from sonogym.outputs import OutputPathError, check_folder, undo_on_failure

    if not re.fullmatch(r"[a-z0-9][a-z0-9_-]*", name):
        raise ValueError(f"name {name!r}: use lower-case letters, digits, '_' and '-'")
    run = Path(run)
    cfg = run_config(run)
    selection = read_selection(run)
    checkpoint = resolve_checkpoint(run, checkpoint)  # "selected": sonogym select's choice
    if checkpoint is None and selection is not None:
        checkpoint = run / "checkpoints" / selection["selected"]  # sonogym select's choice
    if checkpoint is None:
        checkpoint = RunFolder(run, RL_RUN).require_checkpoint().path
    checkpoint = Path(checkpoint)
    if not checkpoint.is_file():
        raise FileNotFoundError(f"checkpoint {checkpoint} not found")
    step = RL_RUN.step_of(checkpoint)
    dest = Path(root) / name
    check_folder(dest, "pretrained policy folder", "give --to a folder you can write to")
    present = [f for f in EXPORTED if (dest / f).exists()]
    if present and not force:
        raise OutputPathError(
            f"{dest} already holds pretrained policy {name!r} ({', '.join(present)}); pass "
            "--force to replace those files (other files there are kept), or give another "
            "--name or --to"
        )
    kept = sorted(p.name for p in dest.iterdir() if p.name not in EXPORTED) if dest.is_dir() else []
    times = read_times(run / "checkpoints").get(step, {}) if step is not None else {}
    shipped_cfg = dict(cfg)
    if cfg.get("init_from"):
        shipped_cfg["init_from"] = _source(cfg["init_from"])  # names, not this machine's paths
    card = _card(name, shipped_cfg, run, checkpoint, step, times, notes)
    card["selection"] = _selection_entry(selection, checkpoint, card["evaluations"])
    saved = RunFolder(run, RL_RUN).checkpoints()
    card["run_reached_steps_per_env"] = saved[-1][0] if saved else step
    tmp = dest.with_name(f".{name}.partial{os.getpid()}")
    with undo_on_failure(tmp, dest):
        tmp.mkdir(parents=True)
        export_acting_weights(checkpoint, tmp / WEIGHTS, acting_modules(cfg["algo"]))
        atomic_write_json(tmp / "config.json", shipped_cfg)
        atomic_write_json(tmp / CARD, card)
        atomic_write_text(tmp / "model_card.md", card_markdown(card))
        dest.mkdir(exist_ok=True)
        for f in EXPORTED:
            os.replace(tmp / f, dest / f)
        tmp.rmdir()
    if kept:
        log(f"kept {', '.join(kept)} in {dest} (sonogym export writes only {', '.join(EXPORTED)})")
    for line in _warnings(run, card):
        warn(line)
    return dest


def _selection_entry(selection, checkpoint: Path, evaluations: dict) -> dict | None:
    """How the exported checkpoint was chosen (``sonogym select``), for the card; None when
    it was not selected so. An evaluation on a selection patient is refused: its figure would
    not be a test of the chosen checkpoint."""
    if selection is None or selection["selected"] != checkpoint.name:
        return None
    leaked = tested_on_selection(selection, evaluations)
    if leaked:
        raise ValueError(
            f"{checkpoint.name} was selected on patients that evaluation {'; '.join(leaked)} "
            "tests on; its figure would not be a test. Evaluate on other patients (remove "
            "that eval*.json) or select on other patients, then export again"
        )
    keys = ("metric", "better", "patients", "trials", "seed")
    return {k: selection[k] for k in keys}


def _warnings(run: Path, card: dict[str, Any]) -> list[str]:
    """What a user should know about an exported policy: a checkpoint short of the run's
    planned steps, a checkpoint never evaluated."""
    out = []
    progress = _progress_text(card)
    if "planned" in progress and "all" not in progress:
        out.append(f"{card['checkpoint']} of {run} is at {progress.removeprefix(', ')}")
    if not card["evaluations"]:
        out.append(
            f"{card['checkpoint']} of {run} has no evaluation (eval*.json), so the model card "
            f"lists none; run sonogym eval --run {run} and export again to include one"
        )
    return out


def _card(name, cfg, run: Path, checkpoint: Path, step, times, notes) -> dict[str, Any]:
    tc = cfg["task_config"]
    env = tc.get("env_kwargs", {})
    evals = {}
    for f in sorted(run.glob("eval*.json")):
        table = json.loads(f.read_text())
        if table.get("checkpoint") not in (None, checkpoint.name):
            continue  # an evaluation of another checkpoint says nothing of this one
        results = table.get("results", {})
        evals[table.get("protocol", f.stem)] = {
            "trials": table.get("trials"),
            # with trials, the seed and env count fix the starts (absent in older tables)
            "seed": table.get("seed"),
            "num_envs": table.get("num_envs"),
            "checkpoint": table.get("checkpoint"),
            "test_env": table.get("env_overrides", {}),
            "results": results,
        }
    steps = step if step is not None else cfg.get("steps")
    return {
        "name": name,
        "task": cfg["task"],
        "algo": cfg["algo"],
        "seed": cfg["seed"],
        "obs_mode": env.get("obs_mode"),
        "net": tc.get("net"),
        "preset": cfg.get("preset"),
        "training_patients": env.get("patients", [0]),
        "imaging_randomization": env.get("imaging_randomization", False),
        "num_envs": tc.get("num_envs"),
        "steps_per_env": steps,
        # how far the run got: the steps it was started for (fewer done: it stopped early)
        "planned_steps_per_env": cfg.get("steps"),
        "steps_total": None if steps is None else steps * int(tc.get("num_envs") or 1),
        "cpu_minutes": round(times["cpu_s"] / 60, 1) if "cpu_s" in times else None,
        "wall_minutes": round(times["wall_s"] / 60, 1) if "wall_s" in times else None,
        "checkpoint": checkpoint.name,
        # a fine-tuned run: where its weights started (their steps are not in steps_per_env;
        # their CPU time is in cpu_minutes)
        "init_from": cfg.get("init_from"),
        "evaluations": evals,
        "headline": _headline(cfg["task"], evals),
        "notes": notes,
        "versions": cfg.get("versions", {}),
    }


def _source(init: dict) -> dict:
    """The run a fine-tuned run started from, by names only (no local paths in a card)."""
    return {
        "run": Path(init["run"]).name,
        "checkpoint": Path(init["checkpoint"]).name,
        "steps_per_env": init.get("steps"),
        "cpu_minutes": round(init["cpu_s"] / 60, 1) if "cpu_s" in init else None,
    }


def _selection_line(sel: dict | None) -> list[str]:
    if not sel:
        return []
    return [
        f"- checkpoint chosen by `sonogym select` on patients {', '.join(sel['patients'])} "
        f"({sel['better']} {sel['metric']}, {sel['trials']} episodes from seed {sel['seed']}), "
        "none of which an evaluation below tests on"
    ]


def _init_from_line(init: dict | None) -> list[str]:
    if not init:
        return []
    return [
        f"- fine-tuned from {init['checkpoint']} of run {init['run']} ({init['steps_per_env']} "
        f"env steps per env, {init['cpu_minutes']} CPU minutes, counted above)"
    ]


def _headline(task: str, evals: dict) -> str:
    from sonogym.envs.registry import get_task

    parts = []
    metrics = get_task(task).metrics
    for proto, e in evals.items():
        pol = e["results"].get("policy", {})
        vals = [f"{m.label} {pol[m.key][0]:.1f} {m.unit}" for m in metrics if m.key in pol]
        if vals:
            parts.append(f"{proto}: " + ", ".join(vals))
    return "; ".join(parts)


def _progress_text(card: dict[str, Any]) -> str:
    """How far the run got, for the card: the checkpoint's share of the planned steps and, short
    of them, whether the run stopped there or went on."""
    done, planned = card.get("steps_per_env"), card.get("planned_steps_per_env")
    if done is None or not planned:
        return ""
    if done >= planned:
        return f", all {planned} planned"
    reached = card.get("run_reached_steps_per_env") or done
    where = "the run stopped there" if reached <= done else f"the run went on to {reached}"
    return f", {100 * done / planned:.0f} % of the {planned} planned ({where})"


def card_markdown(card: dict[str, Any]) -> str:
    """The model card as Markdown."""
    lines = [
        f"# Pretrained policy `{card['name']}`",
        "",
        f"- task: {card['task']}; algorithm: {card['algo']} (seed {card['seed']}); "
        f"observation: {card.get('obs_mode') or 'the task default'}; network: {card.get('net')}",
        f"- trained on patients {card['training_patients']}, imaging randomisation "
        f"{'on' if card['imaging_randomization'] else 'off'}, {card.get('num_envs')} envs",
        f"- {card.get('steps_per_env')} env steps per env ({card.get('steps_total')} in all)"
        f"{_progress_text(card)}, {card.get('cpu_minutes')} CPU minutes "
        f"({card.get('wall_minutes')} wall); checkpoint {card['checkpoint']}",
        *_init_from_line(card.get("init_from")),
        *_selection_line(card.get("selection")),
        f"- evaluate: `sonogym eval --pretrained {card['name']} --out DIR` (add `--patients` "
        "for your own subjects)",
        "",
        "## Evaluations",
        "",
    ]
    if not card["evaluations"]:
        lines += [
            "None: this checkpoint had not been evaluated when it was exported (`sonogym eval "
            "--run RUN` writes an evaluation; export again to include it).",
            "",
        ]
    for proto, e in card["evaluations"].items():
        drawn = [f"{e['trials']} episodes"]  # and what draws the same starts again
        drawn += [f"seed {e['seed']}"] if e.get("seed") is not None else []
        drawn += [f"{e['num_envs']} envs"] if e.get("num_envs") else []
        lines += [f"### {proto} ({', '.join(drawn)}, checkpoint {e['checkpoint']})", ""]
        if e.get("test_env"):
            lines += [f"test env options: `{json.dumps(e['test_env'])}`", ""]
        rows = e["results"]
        keys = sorted({k for r in rows.values() for k in r})
        lines.append("| controller | " + " | ".join(keys) + " |")
        lines.append("|---" * (len(keys) + 1) + "|")
        for c, r in rows.items():
            vals = [f"{r[k][0]:.2f} ± {r[k][1]:.2f}" if k in r else "" for k in keys]
            lines.append(f"| {c} | " + " | ".join(vals) + " |")
        lines.append("")
    if card.get("notes"):
        lines += ["## Notes", "", card["notes"], ""]
    return "\n".join(lines)
