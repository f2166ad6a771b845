"""``sonogym reproduce NAME``: the commands that make each published result, in order.

A recipe is a list of ``sonogym`` commands (train, record, il-train, sweep, eval, report, plot)
exactly as docs/results.md prints them beside the result. ``reproduce`` runs them one after
another, each in its own process, and skips a command whose output is already complete:

* ``train``: the run's checkpoint at the final step (``agent_<steps>.pt``); a run folder
  without it is continued with ``--resume``;
* ``il-train``: the run's ``step_<steps>.pt``; a partial run continues with ``--resume``;
* ``record``: the dataset's ``meta/info.json`` holds the asked number of episodes; a partial
  dataset continues with ``--resume``;
* ``sweep``: its ``sweep.md``; a sweep folder without it (``sweep.json`` only) continues
  with ``--resume``; ``eval``: its table (``eval.json``, ``eval-<protocol>.json``
  or ``eval-<name>.json``); ``report``: ``report.md``; ``plot``: ``curves.md``, unless a
  command before it in the recipe still has to run (it reads that command's output).

So an interrupted reproduction is resumed by running the same command again. ``--dry-run``
prints the commands with the CPU time each took when the published figure was made (the
project's 2-core CPU, one torch thread per run; docs/results.md gives the load of each).

Presets: ``cpu`` is the recipe as published. ``paper`` trains with the paper's settings
(``--preset paper`` and the paper's step count, from the task's ``TrainingDefaults``) instead
of the CPU recipe's steps, network, env count and image pooling, and writes under
``runs/paper/`` and ``reports/paper/``; its CPU time is the CPU recipe's scaled by the env
steps, an order of magnitude for planning (the paper's runs are meant for a GPU).
"""

from __future__ import annotations

import dataclasses
import json
import shlex
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

#: The presets a recipe can be run with.
PRESETS = ("cpu", "paper")


@dataclasses.dataclass(frozen=True)
class Step:
    """One ``sonogym`` command of a recipe and the CPU minutes it took when published."""

    argv: tuple[str, ...]  # the arguments after ``sonogym``
    cpu_min: float  # CPU minutes measured for the published figure (0: under a minute)

    @property
    def command(self) -> str:
        return "sonogym " + shlex.join(self.argv)

    def option(self, name: str, default: str | None = None) -> str | None:
        """The value given to ``--name`` (the last one if given twice)."""
        value = default
        for i, a in enumerate(self.argv[:-1]):
            if a == name:
                value = self.argv[i + 1]
        return value


def _step(command: str, cpu_min: float = 0.0) -> Step:
    argv = shlex.split(command)
    if argv[0] != "sonogym":
        raise ValueError(f"a recipe step is a sonogym command, not {command!r}")
    return Step(tuple(argv[1:]), cpu_min)


#: CPU minutes of a command without a measured figure: an evaluation of 100 episodes on 50
#: envs, a report or a plot.
DEFAULT_CPU_MINUTES = {"eval": 3.0, "select": 10.0, "report": 1.0, "plot": 1.0}


def _steps(commands: Sequence[str], cpu_min: dict[str, float]) -> list[Step]:
    """One Step per command; a command that makes a folder of ``cpu_min`` (its ``--out``) gets
    that folder's CPU minutes, others ``DEFAULT_CPU_MINUTES``."""
    out = []
    for command in commands:
        s = _step(command)
        minutes = cpu_min.get(s.option("--out") or "", DEFAULT_CPU_MINUTES.get(s.argv[0], 0.0))
        out.append(dataclasses.replace(s, cpu_min=minutes))
    return out


def _surgery_state(seed: int) -> list[str]:
    run = f"runs/surg-state-dist-s{seed}"
    return [
        "sonogym train --task surgery --algo ppo --obs-mode state --net lean --env-option "
        f"unsafe_distance_penalty=100 --seed {seed} --steps 120000 --out {run}",
        f"sonogym eval --run {run} --protocol idt --envs 50",
        f"sonogym eval --run {run} --protocol odt-patient --envs 50",
    ]


_NAV_SMALL = "--envs 64 --seed 0 --net small --threads 1 --obs-downsample 4"
_NAV_SWEEP = "--preset cpu --steps 2400 --max-concurrent 1"


@dataclasses.dataclass(frozen=True)
class Recipe:
    """A published result and the commands that make it, in order."""

    name: str  # what `sonogym reproduce` takes
    result: str  # the table or figure of docs/results.md it makes
    commands: tuple[str, ...]


_RECIPES = (
    Recipe(
        "table1",
        "Table 1: surgery (MB rows)",
        (
            *_surgery_state(0),
            *_surgery_state(1),
            *_surgery_state(2),
            "sonogym train --task surgery --algo ppo-sf --obs-downsample 2 --steps 51968 --seed 0 "
            "--net small --env-option unsafe_distance_penalty=0 --out runs/surg-img-w5-s0",
            "sonogym eval --run runs/surg-img-w5-s0 --protocol idt --envs 50",
            "sonogym eval --run runs/surg-img-w5-s0 --protocol odt-patient --envs 50",
            "sonogym eval --run runs/surg-img-w5-s0 --protocol idt --envs 50 --filter-mode zero "
            "--name idt-zero",
            "sonogym record --task surgery --recipe mb --episodes 150 --envs 16 "
            "--out runs/ds-surg-mb",
            "sonogym il-train --policy act --data runs/ds-surg-mb --steps 30000 --threads 1 "
            "--out runs/il-surg-act",
            "sonogym eval --run runs/il-surg-act --envs 50",
            "sonogym eval --run runs/il-surg-act --protocol odt-patient --envs 50",
            "sonogym report --task surgery --runs runs/surg-state-dist-s0 runs/surg-state-dist-s1 "
            "runs/surg-state-dist-s2 runs/surg-img-w5-s0 runs/il-surg-act "
            "--out docs/results/surgery-dist",
        ),
    ),
    Recipe(
        "navigation",
        "Navigation bar chart",
        (
            f"sonogym train --task navigation --algo ppo {_NAV_SMALL} --steps 9024 "
            "--out runs/nav-ppo-small-s0",
            f"sonogym train --task navigation --algo ppo {_NAV_SMALL} --steps 4512 "
            "--protocol odt-sim --out runs/nav-ppo-small-lb-s0",
            "sonogym eval --run runs/nav-ppo-small-s0 --protocol idt",
            "sonogym eval --run runs/nav-ppo-small-s0 --protocol odt-patient",
            "sonogym eval --run runs/nav-ppo-small-lb-s0 --protocol idt",
            "sonogym eval --run runs/nav-ppo-small-lb-s0 --protocol odt-sim",
            "sonogym report --task navigation --runs runs/nav-ppo-small-s0 "
            "runs/nav-ppo-small-lb-s0 --out docs/results/navigation",
        ),
    ),
    Recipe(
        "reconstruction",
        "Reconstruction bar chart and trajectories",
        (
            "sonogym train --task reconstruction --algo ppo --envs 64 --steps 4000 --seed 0 "
            "--net small --threads 1 --out runs/recon-ppo-small-s0",
            "sonogym eval --run runs/recon-ppo-small-s0 --protocol idt",
            "sonogym report --task reconstruction --runs runs/recon-ppo-small-s0 "
            "--out docs/results/reconstruction",
        ),
    ),
    Recipe(
        "population",
        "Across a population (navigation on held-out phantoms and a real subject)",
        (
            "sonogym train --task navigation --algo ppo --preset cpu --patients 100-163 "
            "--obs-mode us_scan --net lean --env-option imaging_randomization=true --seed 0 "
            "--steps 23552 --checkpoint-every 2944 --out runs/nav-pop64-scan-s0",
            "sonogym train --task navigation --algo ppo --preset cpu --patients 100-163 "
            "--obs-mode us_scan --net lean --env-option imaging_randomization=true --seed 0 "
            "--steps 6400 --checkpoint-every 1600 "
            "--init-from runs/nav-pop64-scan-s0/checkpoints/agent_23552.pt "
            "--out runs/nav-pop64-lobes-ft-s0",
            # the checkpoint chosen on phantoms and real-derived variants no figure reports
            "sonogym select --run runs/nav-pop64-lobes-ft-s0 --patients 900-904 "
            "--patients tests/data/totalsegmentator_example@1 "
            "--patients tests/data/totalsegmentator_example@2 --envs 25",
            "sonogym eval --run runs/nav-pop64-lobes-ft-s0 --checkpoint selected --envs 50 "
            "--protocol odt-patient --held-out 5",
            "sonogym eval --run runs/nav-pop64-lobes-ft-s0 --checkpoint selected --envs 50 "
            "--patients tests/data/totalsegmentator_example --name real-subject",
        ),
    ),
    Recipe(
        "imitation",
        "Imitation learning beside RL (navigation)",
        (
            f"sonogym sweep --task navigation --algo ppo --seeds 3 {_NAV_SWEEP} "
            "--out runs/sweep-nav-ppo",
            "sonogym record --task navigation --recipe mb --episodes 1000 --envs 16 "
            "--out runs/ds-nav-mb-1000",
            "sonogym il-train --policy act --data runs/ds-nav-mb-1000 --image-size 100x75 "
            "--steps 128000 --threads 1 --out runs/il-nav-act-1000",
            "sonogym il-train --policy diffusion --data runs/ds-nav-mb-1000 --image-size 100x75 "
            "--steps 80000 --threads 1 --out runs/il-nav-dp-1000",
            "sonogym report --task navigation --runs runs/sweep-nav-ppo/runs runs/il-nav-act-1000 "
            "runs/il-nav-dp-1000 --out docs/results/navigation-il --no-curves",
        ),
    ),
    Recipe(
        "curves",
        "Learning curves and the seeds sweep (navigation)",
        (
            f"sonogym sweep --task navigation --algo ppo --seeds 3 {_NAV_SWEEP} "
            "--out runs/sweep-nav-ppo",
            f"sonogym sweep --task navigation --algo a2c --seeds 1 {_NAV_SWEEP} "
            "--out runs/sweep-nav-a2c",
            "sonogym plot --runs runs/sweep-nav-ppo/runs runs/sweep-nav-a2c/runs "
            "--out docs/results/navigation-sweep --metric 'Episode / return' "
            "--metric 'Episode / position_error_mm'",
        ),
    ),
    Recipe(
        "table1-lb",
        "Table 1: surgery (LB rows: trained on learned nets 0-3, ODT on net 4)",
        (
            "sonogym train --task surgery --algo ppo-sf --obs-downsample 2 --steps 51968 --seed 0 "
            "--net small --env-option unsafe_distance_penalty=0 --protocol odt-sim "
            "--out runs/surg-img-lb-s0",
            "sonogym eval --run runs/surg-img-lb-s0 --protocol idt --envs 50",
            "sonogym eval --run runs/surg-img-lb-s0 --protocol odt-sim --envs 50",
            "sonogym record --task surgery --recipe lb-4-nets --episodes 150 --envs 16 "
            "--out runs/ds-surg-lb",
            "sonogym il-train --policy act --data runs/ds-surg-lb --steps 30000 --threads 1 "
            "--out runs/il-surg-act-lb",
            "sonogym eval --run runs/il-surg-act-lb --envs 50",
            "sonogym eval --run runs/il-surg-act-lb --protocol odt-sim --envs 50",
            "sonogym report --task surgery --runs runs/surg-state-dist-s0 runs/surg-state-dist-s1 "
            "runs/surg-state-dist-s2 runs/surg-img-w5-s0 runs/il-surg-act runs/surg-img-lb-s0 "
            "runs/il-surg-act-lb --out docs/results/surgery-table1",
        ),
    ),
    Recipe(
        "navigation-lb",
        "Navigation on the learned simulator (PPO, ACT, Diffusion Policy; ODT on net 4)",
        (
            f"sonogym train --task navigation --algo ppo {_NAV_SMALL} --steps 4512 "
            "--protocol odt-sim --out runs/nav-ppo-small-lb-s0",
            "sonogym eval --run runs/nav-ppo-small-lb-s0 --protocol idt",
            "sonogym eval --run runs/nav-ppo-small-lb-s0 --protocol odt-sim",
            "sonogym record --task navigation --recipe lb-4-nets --episodes 1000 --envs 16 "
            "--out runs/ds-nav-lb-1000",
            "sonogym il-train --policy act --data runs/ds-nav-lb-1000 --image-size 100x75 "
            "--steps 128000 --threads 1 --out runs/il-nav-act-lb-1000",
            "sonogym il-train --policy diffusion --data runs/ds-nav-lb-1000 --image-size 100x75 "
            "--steps 80000 --threads 1 --out runs/il-nav-dp-lb-1000",
            "sonogym eval --run runs/il-nav-act-lb-1000 --protocol idt",
            "sonogym eval --run runs/il-nav-act-lb-1000 --protocol odt-sim",
            "sonogym eval --run runs/il-nav-dp-lb-1000 --protocol idt",
            "sonogym eval --run runs/il-nav-dp-lb-1000 --protocol odt-sim",
            "sonogym report --task navigation --runs runs/nav-ppo-small-lb-s0 "
            "runs/il-nav-act-lb-1000 runs/il-nav-dp-lb-1000 --out docs/results/navigation-lb "
            "--no-curves",
        ),
    ),
)

#: Every published result's recipe by name (docs/results.md prints the same commands).
RECIPES: dict[str, Recipe] = {r.name: r for r in _RECIPES}
#: ``sonogym reproduce all``: every recipe, in this order (model-based results first).
ALL = "all"


#: CPU minutes of each run when its published figure was made (docs/results.md); evaluations,
#: reports and plots take a minute or a few.
CPU_MINUTES: dict[str, float] = {
    **{f"runs/surg-state-dist-s{s}": m for s, m in enumerate((28.9, 28.6, 29.8))},
    "runs/surg-img-w5-s0": 98.2,
    "runs/ds-surg-mb": 1.5,
    "runs/il-surg-act": 27.0,
    "runs/nav-ppo-small-s0": 45.0,
    "runs/nav-ppo-small-lb-s0": 27.0,
    "runs/recon-ppo-small-s0": 27.0,
    # the shipped navigation policy's recipe (its model card)
    "runs/nav-pop64-scan-s0": 139.1,
    "runs/nav-pop64-lobes-ft-s0": 35.4,
    "runs/sweep-nav-ppo": 15.0,
    "runs/sweep-nav-a2c": 5.0,
    "runs/ds-nav-mb-1000": 19.4,
    "runs/il-nav-act-1000": 82.9,
    "runs/il-nav-dp-1000": 79.5,
    # learned-simulator results: estimates (the model-based figure over the learned
    # simulator's env speed, ~0.5x), until measured
    "runs/surg-img-lb-s0": 200.0,
    "runs/ds-surg-lb": 3.0,
    "runs/il-surg-act-lb": 27.0,
    "runs/ds-nav-lb-1000": 40.0,
    "runs/il-nav-act-lb-1000": 83.0,
    "runs/il-nav-dp-lb-1000": 80.0,
}


def recipe(name: str, preset: str = "cpu") -> list[Step]:
    """The steps of result ``name`` under ``preset`` ("cpu" or "paper")."""
    if name not in RECIPES:
        raise ValueError(
            f"no result named {name!r}; choose one of {', '.join(RECIPES)}, or {ALL} for every one"
        )
    if preset not in PRESETS:
        raise ValueError(f"preset {preset!r}: choose one of {', '.join(PRESETS)}")
    steps = _steps(RECIPES[name].commands, CPU_MINUTES)
    return steps if preset == "cpu" else [_paper(s) for s in steps]


# Options of a CPU recipe's training command that the paper preset sets instead.
_CPU_TRAINING_OPTIONS = ("--steps", "--net", "--envs", "--preset", "--obs-downsample", "--threads")


#: Where the paper preset writes instead, so its runs and reports never mix with the CPU
#: recipe's (or overwrite the published figures).
_PAPER_FOLDERS = (("runs/", "runs/paper/"), ("docs/results/", "reports/paper/"))


def _paper(step: Step) -> Step:
    """``step`` under the paper preset: training with ``--preset paper`` and the paper's step
    count in place of the CPU recipe's steps, network, env count and image pooling; every
    output under ``runs/paper/`` and ``reports/paper/``."""
    argv = [_paper_path(a) for a in step.argv]
    if step.argv[0] not in ("train", "sweep"):
        return Step(tuple(argv), step.cpu_min)
    kept, i = [], 0
    while i < len(argv):
        if argv[i] in _CPU_TRAINING_OPTIONS:
            i += 2
            continue
        kept.append(argv[i])
        i += 1
    timesteps, num_envs = _paper_schedule(step.option("--task", "navigation"))
    kept += ["--preset", "paper", "--steps", str(timesteps)]
    cpu_steps = float(step.option("--steps", "0") or 0) * int(step.option("--envs", "64") or 64)
    scale = timesteps * num_envs / cpu_steps if cpu_steps else 0.0
    return Step(tuple(kept), round(step.cpu_min * scale, 1))


def _paper_path(arg: str) -> str:
    for cpu, paper in _PAPER_FOLDERS:
        if arg.startswith(cpu):
            return paper + arg[len(cpu) :]
    return arg


def _paper_schedule(task: str) -> tuple[int, int]:
    """(env steps per env, envs) of the task's paper preset."""
    from sonogym.agents.configs import task_config

    cfg = task_config(task, "paper")
    return int(cfg.timesteps), int(cfg.num_envs)


# ----------------------------------------------------------------------------- done checks


def _out(step: Step) -> Path:
    return Path(step.option("--out") or step.option("--run") or ".")


def _eval_table(step: Step) -> Path:
    from sonogym.evaluation.rl_eval import table_stem

    name = step.option("--name") or step.option("--protocol", "idt")
    return _out(step) / f"{table_stem(name)}.json"


def _records(path: Path) -> int:
    """Episodes the dataset at ``path`` has committed (0: none, or no dataset yet); read
    leniently: ``record --resume`` checks the dataset itself."""
    try:
        return int(json.loads((path / "meta" / "info.json").read_text())["total_episodes"])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


#: The file a command writes last, whose presence means it finished.
_FINAL_FILE = {"report": "report.md", "plot": "curves.md", "sweep": "sweep.md"}


def _read(path: Path) -> dict:
    """A JSON file's object, {} when absent or unreadable (a status check reads leniently)."""
    try:
        obj = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return obj if isinstance(obj, dict) else {}


def _today(task: Any, env_kwargs: Any) -> dict | None:
    """The identity ``task``'s env with ``env_kwargs`` (as a JSON file holds them) has today;
    None where they do not describe one (an unknown task, an option no longer accepted)."""
    from sonogym.envs.identity import identity
    from sonogym.runs import lists_to_tuples

    try:
        return identity(str(task), lists_to_tuples(env_kwargs or {}))
    except (ValueError, TypeError, KeyError, OSError):
        return None


def _recording_identity(dataset: Path) -> dict | None:
    """The identity a dataset would be recorded under today, from how it was recorded."""
    meta = _read(dataset / "meta" / "sonogym.json")
    return _today(meta.get("task"), meta.get("env_kwargs"))


def made_under_another_identity(step: Step) -> bool:
    """Whether the output ``step`` left was made under a benchmark identity other than today's
    for the same options (or records none: an older sonogym). An absent output is not."""
    from sonogym.envs.identity import IDENTITY_FILE

    def differs(recorded, today) -> bool:
        return recorded is None or recorded != today

    cmd, out = step.argv[0], _out(step)
    if cmd == "train" and (out / "config.json").is_file():
        cfg = _read(out / "config.json")
        env = cfg.get("task_config", {}).get("env_kwargs")
        return differs(cfg.get("identity"), _today(cfg.get("task"), env))
    if cmd == "record" and (out / "meta" / "sonogym.json").is_file():
        meta = _read(out / "meta" / "sonogym.json")
        return differs(meta.get("identity"), _recording_identity(out))
    if cmd == "il-train" and (out / "config.json").is_file():
        data = Path(step.option("--data") or "")
        return differs(_read(out / "config.json").get("identity"), _recording_identity(data))
    if cmd == "eval" and _eval_table(step).is_file():
        table = _read(_eval_table(step))
        run = _read(out / "config.json")
        return differs(
            table.get("identity"), _today(table.get("task"), table.get("test_env"))
        ) or differs(table.get("train_identity"), run.get("identity"))
    if cmd == "sweep" and (out / _FINAL_FILE["sweep"]).is_file():
        runs = [c.parent for c in (out / "runs").glob("*/config.json")]
        return not runs or any(made_under_another_identity(_train_step(r)) for r in runs)
    if cmd in ("report", "plot") and (out / _FINAL_FILE[cmd]).is_file():
        return not (out / IDENTITY_FILE).is_file()
    return False


def _train_step(run: Path) -> Step:
    return Step(("train", "--out", str(run)), 0.0)


def status(step: Step) -> str:
    """ "done", "partial" (an output to continue with ``--resume``), "stale" (an output made
    under another benchmark identity, to make anew with ``--force``) or "todo"."""
    if made_under_another_identity(step):
        return "stale"
    cmd, out = step.argv[0], _out(step)
    if cmd == "eval":
        return "done" if _eval_table(step).is_file() else "todo"
    if cmd == "select":
        from sonogym.evaluation.selection import SELECTION

        return "done" if (out / SELECTION).is_file() else "todo"
    if cmd == "sweep" and not (out / _FINAL_FILE[cmd]).is_file():
        from sonogym.agents.sweep import SWEEP_FILE

        return "partial" if (out / SWEEP_FILE).is_file() else "todo"
    if cmd in _FINAL_FILE:
        return "done" if (out / _FINAL_FILE[cmd]).is_file() else "todo"
    if cmd == "record":
        n = _records(out)
        if n >= int(step.option("--episodes", "0") or 0) > 0:
            return "done"
        return "partial" if out.exists() and any(out.iterdir()) else "todo"
    if cmd in ("train", "il-train"):
        steps = step.option("--steps")
        final = f"agent_{steps}.pt" if cmd == "train" else f"step_{int(steps or 0):09d}.pt"
        if steps and (out / "checkpoints" / final).is_file():
            return "done"
        return "partial" if (out / "checkpoints").is_dir() else "todo"
    return "todo"


#: What ``sweep --resume`` still takes: the rest is fixed by the sweep's ``sweep.json``.
_SWEEP_RESUME_OPTIONS = ("--task", "--algo", "--out", "--max-concurrent", "--address")


def _resumed(step: Step) -> tuple[str, ...]:
    """The argv that continues ``step``'s partial output (before ``--resume``): the same
    command, except that a sweep keeps only the options its stored definition does not fix."""
    if step.argv[0] != "sweep":
        return step.argv
    kept = [(k, step.option(k)) for k in _SWEEP_RESUME_OPTIONS if step.option(k) is not None]
    return ("sweep", *(a for kv in kept for a in kv))


#: Commands that replace their output only when told to (``--force``).
_FORCED = ("train", "record", "il-train", "sweep")


def to_run(steps: Sequence[Step]) -> list[tuple[Step, str]]:
    """Each step with its status; the argv of a partial step gets ``--resume``, that of a
    stale one ``--force`` (training, recording, sweeps; evaluations, reports and plots rewrite
    their files). A report or plot after a step still to run is to run again: it reads that
    step's output."""
    out, pending = [], False
    remade: set[Path] = set()  # run folders this plan trains (again)
    for s in steps:
        st = status(s)
        if pending and s.argv[0] in ("report", "plot"):
            st = "todo"
        if s.argv[0] in ("eval", "select") and st != "todo" and _out(s) in remade:
            st = "todo"  # its run is trained again: the table would be of the old one
        if s.argv[0] in ("train", "il-train") and st != "done":
            remade.add(_out(s))
        if st == "partial":
            s = dataclasses.replace(s, argv=(*_resumed(s), "--resume"))
        if st == "stale" and s.argv[0] in _FORCED:
            s = dataclasses.replace(s, argv=(*s.argv, "--force"))
        pending |= st != "done"
        out.append((s, st))
    return out


def reproduce(
    name: str,
    preset: str = "cpu",
    dry_run: bool = False,
    log: Callable[[str], None] = print,
    runner: Callable[[list[str]], int] | None = None,
) -> int:
    """Run (or with ``dry_run`` print) result ``name``'s commands, skipping those done;
    returns the number of commands run. ``name`` "all" runs every recipe in ``RECIPES``'s
    order. A failing command stops the reproduction with its exit status
    (``subprocess.CalledProcessError``)."""
    if name == ALL:
        if preset not in PRESETS:
            recipe(next(iter(RECIPES)), preset)  # the usual error
        plans = {n: to_run(recipe(n, preset)) for n in RECIPES}
        left = sum(s.cpu_min for plan in plans.values() for s, st in plan if st != "done")
        log(f"all {len(RECIPES)} results ({preset} preset): ~{left:.0f} CPU min to go")
        return sum(reproduce(n, preset, dry_run, log, runner) for n in RECIPES)
    plan = to_run(recipe(name, preset))
    total = sum(s.cpu_min for s, st in plan if st != "done")
    log(f"{name}, {RECIPES[name].result} ({preset} preset): {len(plan)} commands, "
        f"{sum(st == 'done' for _, st in plan)} done, ~{total:.0f} CPU min to go")  # fmt: skip
    ran = 0
    for s, st in plan:
        cost = f"~{s.cpu_min:.0f} CPU min" if s.cpu_min else "< a few CPU min"
        if st == "done":
            log(f"  done     {s.command}")
            continue
        verb = {"partial": "resume", "stale": "redo"}.get(st, "run")
        log(f"  {verb:8} {s.command}   # {cost}")
        if dry_run:
            continue
        argv = [sys.executable, "-m", "sonogym.cli", *s.argv]
        code = (runner or _run)(argv)
        if code != 0:
            raise subprocess.CalledProcessError(code, s.command)
        ran += 1
    return ran


def _run(argv: list[str]) -> int:
    return subprocess.run(argv, check=False).returncode
