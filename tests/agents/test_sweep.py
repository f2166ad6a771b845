"""`sonogym sweep` on a local Ray: seeds x grid as normal run folders, a table of every trial, a
failing trial reported while the others finish, and a resumed sweep that reruns nothing."""

from __future__ import annotations

import csv

import pytest

pytest.importorskip("ray.tune")

from sonogym.agents.sweep import apply, parse_grid, sweep, trial_name  # noqa: E402
from sonogym.evaluation.trained import load_run  # noqa: E402

TINY = dict(
    preset="cpu",
    envs=2,
    steps=32,
    threads=1,
    env_kwargs=dict(patients=(0,), phantom_spacing=0.002, episode_length=16),
    checkpoint_interval=16,
)


def _rows(out):
    with open(out / "sweep.csv") as f:
        return {r["trial"]: r for r in csv.DictReader(f)}


def test_grid_parsing_and_trial_configs():
    grid = parse_grid(["ppo.learning_rate=1e-4,3e-4", "net=small", "env.episode_length=20"])
    assert grid == {"ppo.learning_rate": [1e-4, 3e-4], "net": ["small"], "env.episode_length": [20]}
    with pytest.raises(ValueError, match="unknown grid key 'lr'"):
        parse_grid(["lr=1"])
    with pytest.raises(ValueError, match="write key=value1,value2"):
        parse_grid(["net"])
    from sonogym.agents.configs import resolve_train_config

    base = resolve_train_config("navigation", "ppo", **TINY)
    cfg = apply(base, {"seed": 2, "ppo.learning_rate": 3e-4, "env.episode_length": 20})
    assert cfg.seed == 2 and cfg.params.learning_rate == 3e-4
    assert cfg.rl.env_kwargs["episode_length"] == 20 and cfg.rl.num_envs == 2
    assert base.params.learning_rate != 3e-4  # the base is untouched
    name = trial_name("navigation", "ppo", {"seed": 2, "ppo.learning_rate": 3e-4})
    assert name == "navigation-ppo-ppo.learning_rate=0.0003-s2"


def test_local_sweep_table_failure_and_resume(tmp_path):
    out = tmp_path / "sweep"
    # one grid value the phantom refuses (0.5 m voxels): that trial errors, the other finishes
    res = sweep(
        "navigation", "ppo", out, seeds=1, grid={"env.phantom_spacing": [0.002, 0.5]},
        log=lambda m: None, **TINY,
    )  # fmt: skip
    status = {r.params["env.phantom_spacing"]: r for r in res.trials}
    assert status[0.002].status == "TERMINATED" and status[0.002].error is None
    assert status[0.5].status == "ERROR" and "spacing" in status[0.5].error
    ok = out / "runs" / status[0.002].name
    assert load_run(ok).seed == 0 and load_run(ok).config["num_envs"] == 2
    ckpts = sorted((ok / "checkpoints").glob("agent_*.pt"))
    assert [p.name for p in ckpts] == ["agent_0.pt", "agent_16.pt", "agent_32.pt"]
    assert status[0.002].metrics["steps"] == 32 and status[0.002].metrics["episodes"] >= 2
    rows = _rows(out)
    assert rows[status[0.002].name]["status"] == "TERMINATED"
    assert rows[status[0.5].name]["status"] == "ERROR"
    assert "failed:" in (out / "sweep.md").read_text()

    # the folder rule: an existing sweep is neither continued nor replaced by accident
    with pytest.raises(FileExistsError, match="--resume"):
        sweep("navigation", "ppo", out, seeds=1, log=lambda m: None, **TINY)

    before = {p: p.stat().st_mtime_ns for p in ckpts}
    again = sweep("navigation", "ppo", out, resume=True, log=lambda m: None)
    assert {p: p.stat().st_mtime_ns for p in ckpts} == before  # nothing was retrained
    assert {r.name: r.status for r in again.trials} == {r.name: r.status for r in res.trials}


def test_cli_resume_refuses_options_that_would_change_the_sweep(tmp_path):
    from typer.testing import CliRunner

    from sonogym.cli import app

    res = CliRunner().invoke(app, ["sweep", "--task", "navigation", "--out", str(tmp_path),
                                   "--resume", "--steps", "10", "--grid", "net=small"])  # fmt: skip
    # the error box wraps (and folds long paths) at the terminal's width: compare without it
    text = "".join(res.output.replace("│", "").split())
    assert res.exit_code != 0
    assert "leaveout--grid,--steps" in text and "sweep.jsondefinesit" in text


def test_a_second_sweep_into_a_folder_in_use_is_refused(tmp_path, folder_in_use):
    out = tmp_path / "sweep"
    first = folder_in_use(out, "sweep")
    with pytest.raises(FileExistsError, match=rf"{out} is in use .*pid {first.pid}"):
        sweep("navigation", "ppo", out, seeds=1, log=lambda m: None, **TINY)
    assert not (out / "sweep.json").exists()


@pytest.mark.parametrize(
    ("grid", "message"),
    [
        ({"ppo.bogus": [1]}, "ppo has no setting 'bogus'"),
        ({"env.bogus": [1]}, "unknown NavigationConfig option(s) ['bogus']"),
        ({"env.episode_length": [20, -1]}, "episode_length must be >= 1"),
        ({"ppo.rollouts": [0]}, "PPOParams.rollouts must be >= 1"),
        ({"net": ["small", "huge"]}, "unknown net 'huge'"),
        ({"ppo.learning_rate": [float("nan")]}, "learning_rate must be a finite number"),
        ({"num_envs": [100_000_000]}, "sweep trials at once needs about"),
    ],
)
def test_every_grid_point_is_checked_before_the_sweep_starts(grid, message, tmp_path):
    """Each of these used to pass the up-front check and error in every trial (exit 0)."""
    import ray

    out = tmp_path / "sweep"
    with pytest.raises(ValueError) as e:
        sweep("navigation", "ppo", out, seeds=2, grid=grid, log=lambda m: None, **TINY)
    assert message in str(e.value)
    assert not out.exists() and not ray.is_initialized()  # nothing written, nothing started


def test_cli_names_a_bad_grid_key_and_fails_when_every_trial_failed(tmp_path):
    from typer.testing import CliRunner

    from sonogym.cli import app

    args = ["sweep", "--task", "navigation", "--seeds", "1", "--preset", "cpu", "--envs", "2",
            "--steps", "16", "--threads", "1", "--patients", "0",
            "--phantom-spacing", "2"]  # fmt: skip
    res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "a"), "--grid", "ppo.bogus=1"])
    assert isinstance(res.exception, ValueError)  # main() prints it as one line, no traceback
    assert "ppo has no setting 'bogus'" in str(res.exception)
    # a value only the phantom refuses (0.5 m voxels) fails in the trial: all trials failed
    out = tmp_path / "b"
    res = CliRunner().invoke(app, [*args, "--out", str(out), "--grid", "env.phantom_spacing=0.5"])
    assert res.exit_code != 0 and isinstance(res.exception, ValueError)
    assert "all 1 trials failed" in str(res.exception) and "spacing" in str(res.exception)
    assert (out / "sweep.md").is_file()  # the table of what failed is still written
