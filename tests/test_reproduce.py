"""`sonogym reproduce`: each result's commands are the ones docs/results.md prints beside it, a
command whose output is complete is skipped, a partial one resumes, and a report follows the
runs it reads."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
from pathlib import Path

import pytest
from typer.testing import CliRunner

from sonogym import reproduce as R
from sonogym.agents.configs import task_config
from sonogym.cli import app
from sonogym.envs.identity import identity

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results.md"


def _documented() -> dict[str, list[tuple[str, ...]]]:
    """Commands of the docs' bash blocks headed ``# sonogym reproduce NAME``, per NAME, in
    document order."""
    found: dict[str, list[tuple[str, ...]]] = {}
    for block in re.findall(r"```bash\n(.*?)```", RESULTS.read_text(), re.S):
        head = re.match(r"# sonogym reproduce ([\w-]+)\n", block)
        if not head:
            continue
        for line in block[head.end() :].replace("\\\n", " ").splitlines():
            argv = shlex.split(line, comments=True)
            if argv:
                assert argv[0] == "sonogym", line
                found.setdefault(head.group(1), []).append(tuple(argv[1:]))
    return found


def test_dry_run_lists_exactly_the_commands_the_docs_print():
    documented = _documented()
    assert sorted(documented) == sorted(R.RECIPES)
    for name in R.RECIPES:
        assert [s.argv for s in R.recipe(name)] == documented[name], name
    res = CliRunner().invoke(app, ["reproduce", "reconstruction", "--dry-run"])
    assert res.exit_code == 0, res.output
    listed = [line.split("#")[0].split(None, 1)[1].strip() for line in res.output.splitlines()[1:]]
    assert listed == [s.command for s in R.recipe("reconstruction")]


def _touch(path: Path, text: str = "") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


_ENV = {"patients": [0], "phantom_spacing": 0.002}
_CURRENT = identity("reconstruction", {"patients": (0,), "phantom_spacing": 0.002})
#: an evaluation table of today's identity, of a run trained under it
_TABLE = json.dumps(
    {"task": "reconstruction", "test_env": _ENV, "identity": _CURRENT, "train_identity": _CURRENT}
)


def _run_config(folder: Path, made_with: dict | None) -> None:
    cfg = {"task": "reconstruction", "task_config": {"env_kwargs": _ENV}}
    if made_with is not None:
        cfg["identity"] = made_with
    _touch(folder / "config.json", json.dumps(cfg))


def test_done_commands_are_skipped_partial_ones_resume_and_reports_follow(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    train, ev, report = R.recipe("reconstruction")
    assert [st for _, st in R.to_run([train, ev, report])] == ["todo", "todo", "todo"]
    _touch(tmp_path / "runs/recon-ppo-small-s0/checkpoints/agent_2000.pt")
    _touch(tmp_path / "docs/results/reconstruction/report.md")
    plan = R.to_run([train, ev, report])
    assert plan[0][0].argv[-1] == "--resume" and plan[0][1] == "partial"
    assert plan[2][1] == "todo"  # the stored report predates runs still to make
    _touch(tmp_path / "runs/recon-ppo-small-s0/checkpoints/agent_4000.pt")  # the final step
    _run_config(tmp_path / "runs/recon-ppo-small-s0", _CURRENT)
    _touch(tmp_path / "runs/recon-ppo-small-s0/eval.json", _TABLE)
    _touch(tmp_path / "docs/results/reconstruction/identity.json", "{}")
    assert [st for _, st in R.to_run([train, ev, report])] == ["done", "done", "done"]

    named = R._step("sonogym eval --run runs/x --protocol idt --name idt-zero")
    assert R.status(named) == "todo"
    _run_config(tmp_path / "runs/x", _CURRENT)
    _touch(tmp_path / "runs/x/eval-idt-zero.json", _TABLE)
    assert R.status(named) == "done"

    record = R._step("sonogym record --task surgery --episodes 150 --out runs/ds")
    _touch(tmp_path / "runs/ds/meta/info.json", json.dumps({"total_episodes": 40}))
    assert R.status(record) == "partial"
    _touch(tmp_path / "runs/ds/meta/info.json", json.dumps({"total_episodes": 150}))
    assert R.status(record) == "done"
    il = R._step("sonogym il-train --policy act --data runs/ds --steps 300 --out runs/il")
    _touch(tmp_path / "runs/il/checkpoints/step_000000100.pt")
    assert R.status(il) == "partial"
    _touch(tmp_path / "runs/il/checkpoints/step_000000300.pt")
    assert R.status(il) == "done"

    select = R._step("sonogym select --run runs/x --patients 900-904")
    assert R.status(select) == "todo"
    _touch(tmp_path / "runs/x/selection.json", "{}")
    assert R.status(select) == "done"

    sweep = R._step("sonogym sweep --task navigation --algo ppo --seeds 3 --out runs/sw")
    assert R.status(sweep) == "todo"
    _touch(tmp_path / "runs/sw/sweep.json", "{}")  # started, interrupted before its summary
    assert R.status(sweep) == "partial"
    # resumed as sweep.json defines it: the options that define a sweep are left out
    assert R.to_run([sweep])[0][0].argv == (
        "sweep",
        "--task",
        "navigation",
        "--algo",
        "ppo",
        "--out",
        "runs/sw",
        "--resume",
    )
    _touch(tmp_path / "runs/sw/sweep.md")
    _run_config(tmp_path / "runs/sw/runs/r0", _CURRENT)
    assert R.status(sweep) == "done"


def test_reproduce_runs_what_is_left_in_order_and_stops_at_a_failure(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _touch(tmp_path / "runs/recon-ppo-small-s0/checkpoints/agent_4000.pt")
    ran = []
    assert R.reproduce("reconstruction", runner=lambda a: ran.append(a[3:]) or 0, log=str) == 2
    assert [a[0] for a in ran] == ["eval", "report"]
    assert ran[0] == ["eval", "--run", "runs/recon-ppo-small-s0", "--protocol", "idt"]
    with pytest.raises(subprocess.CalledProcessError, match="sonogym eval"):
        R.reproduce("reconstruction", runner=lambda a: 3, log=str)
    res = CliRunner().invoke(app, ["reproduce", "table2", "--dry-run"])
    assert res.exit_code != 0 and "table1" in res.output


def test_paper_preset_trains_with_the_papers_schedule_in_its_own_folders():
    paper = R.recipe("navigation", "paper")
    cfg = task_config("navigation", "paper")
    train = paper[0]
    assert train.option("--preset") == "paper" and train.option("--steps") == str(cfg.timesteps)
    for option in ("--net", "--envs", "--obs-downsample", "--threads"):
        assert train.option(option) is None, option
    assert train.option("--out") == "runs/paper/nav-ppo-small-s0"
    assert paper[-1].option("--out") == "reports/paper/navigation"
    assert all(not a.startswith(("runs/nav", "docs/")) for s in paper for a in s.argv)
    cpu = R.recipe("navigation")[0]
    assert train.cpu_min == pytest.approx(
        cpu.cpu_min * cfg.timesteps * cfg.num_envs / (9024 * 64), rel=1e-3
    )


def test_outputs_of_another_identity_are_made_anew(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    train, ev, report = R.recipe("reconstruction")
    run = tmp_path / "runs/recon-ppo-small-s0"
    current, table = _CURRENT, json.loads(_TABLE)
    _run_config(run, current)
    _touch(run / "checkpoints/agent_4000.pt")
    _touch(run / "eval.json", _TABLE)
    _touch(tmp_path / "docs/results/reconstruction/report.md")
    _touch(tmp_path / "docs/results/reconstruction/identity.json", "{}")
    assert [st for _, st in R.to_run([train, ev, report])] == ["done", "done", "done"]

    # the same run trained under an older task definition: trained anew, then evaluated and
    # reported anew
    _run_config(run, {**current, "task_version": current["task_version"] - 1})
    plan = R.to_run([train, ev, report])
    assert [st for _, st in plan] == ["stale", "todo", "todo"]
    assert plan[0][0].argv[-1] == "--force"
    _run_config(run, None)  # made before identities were recorded
    assert R.status(train) == "stale"

    # an evaluation of today's run made under another identity, and a report without one
    _run_config(run, current)
    _touch(run / "eval.json", json.dumps({**table, "identity": {**current, "task_version": 0}}))
    (tmp_path / "docs/results/reconstruction/identity.json").unlink()
    assert [st for _, st in R.to_run([train, ev, report])] == ["done", "stale", "todo"]


def test_reproduce_all_runs_every_recipe_in_order(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    lines = []
    R.reproduce("all", dry_run=True, log=lines.append)
    assert lines[0].startswith(f"all {len(R.RECIPES)} results")
    heads = [ln.split(",")[0] for ln in lines if not ln.startswith(("  ", "all "))]
    assert heads == list(R.RECIPES)
    assert list(R.RECIPES)[-2:] == ["table1-lb", "navigation-lb"]
    res = CliRunner().invoke(app, ["reproduce", "all", "--dry-run"])
    assert res.exit_code == 0 and "navigation-lb" in res.output
