"""No lost runs, no code from files: atomic checkpoints, unreadable ones skipped by name,
resume that refuses changed options before touching anything, Ctrl-C that saves, and
checkpoints that never unpickle code."""

from __future__ import annotations

import json
import pickle

import pytest
import torch
from typer.testing import CliRunner

from sonogym.agents.checkpoint import CheckpointError, read_checkpoint
from sonogym.agents.train import TrainingInterrupted, train
from sonogym.cli import app
from sonogym.evaluation.rl_eval import evaluate_run

FAST = dict(phantom_spacing=0.002, episode_length=10)


def _tiny(out, steps=32, **kw):
    torch.set_num_threads(1)
    args = dict(envs=2, steps=steps, out=out, patients=(0,), obs_downsample=4, progress=False)
    args["env_kwargs"] = dict(FAST)
    return train("navigation", "ppo", **{**args, **kw})


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("safety") / "nav"
    _tiny(out)
    return out


def test_a_torn_newest_checkpoint_is_skipped_by_name_and_one_can_be_picked(run, tmp_path):
    import shutil

    r = tmp_path / "r"
    shutil.copytree(run, r)
    (r / "checkpoints" / "agent_999.pt").write_bytes(b"")  # a save killed half-way
    with pytest.warns(UserWarning, match="agent_999.pt"):
        res = evaluate_run(r, trials=2, envs=2, controllers=("policy",), plot=False)
    assert json.loads((r / "eval.json").read_text())["results"] == {
        "policy": {k: list(v) for k, v in res["policy"].items()}
    }
    # an explicit checkpoint is used as given
    evaluate_run(r, trials=2, envs=2, controllers=("policy",), plot=False,
                 checkpoint=r / "checkpoints" / "agent_0.pt")  # fmt: skip
    torn = str(r / "checkpoints" / "agent_999.pt")
    args = ["eval", "--run", str(r), "--trials", "2", "--envs", "2", "--checkpoint", torn]
    res = CliRunner().invoke(app, args)
    assert res.exit_code != 0 and "agent_999.pt" in res.output


def test_resume_refuses_changed_options_before_touching_the_run(run, tmp_path):
    import shutil

    r = tmp_path / "r"
    shutil.copytree(run, r)
    before = (r / "config.json").read_bytes()
    for bad, name in ((dict(net="paper"), "net"), (dict(obs_downsample=2), "obs_downsample"),
                      (dict(envs=4), "envs"), (dict(patients=(1,)), "patients")):  # fmt: skip
        with pytest.raises(ValueError, match=name):
            _tiny(r, steps=64, resume=True, **bad)
        assert (r / "config.json").read_bytes() == before  # untouched: the run still evaluates
    # the same options, or only longer: continues
    res = _tiny(r, steps=64, resume=True)
    assert res.steps == 64 and json.loads((r / "config.json").read_text())["resumed_from"] == 32


def test_existing_run_needs_resume_or_force(run, tmp_path):
    import shutil

    r = tmp_path / "r"
    shutil.copytree(run, r)
    with pytest.raises(FileExistsError, match="--resume.*--force"):
        _tiny(r)
    _tiny(r, steps=16, force=True)  # replaced: a fresh run of 16 steps
    names = sorted(p.name for p in (r / "checkpoints").iterdir())
    assert names == ["agent_0.pt", "agent_16.pt", "times.json"]
    with pytest.raises(FileNotFoundError, match="nothing to resume"):
        _tiny(tmp_path / "new", resume=True)


def test_ctrl_c_saves_a_checkpoint_and_says_how_to_resume(tmp_path, monkeypatch):
    from sonogym.agents import adapter as adapter_mod

    real_step = adapter_mod.SkrlEnvAdapter.step
    calls = {"n": 0}

    def step(self, actions):
        calls["n"] += 1
        if calls["n"] == 13:
            raise KeyboardInterrupt
        return real_step(self, actions)

    monkeypatch.setattr(adapter_mod.SkrlEnvAdapter, "step", step)
    logged = []
    with pytest.raises(TrainingInterrupted, match="--resume"):
        _tiny(tmp_path / "r", log=logged.append)
    assert (tmp_path / "r" / "checkpoints" / "agent_12.pt").is_file()  # 12 completed steps
    assert "agent_12.pt" in logged[-1] and "--resume" in logged[-1]
    monkeypatch.setattr(adapter_mod.SkrlEnvAdapter, "step", real_step)
    assert _tiny(tmp_path / "r", resume=True).steps == 32


class _Payload:
    def __reduce__(self):  # what a hostile checkpoint would carry
        return (open, ("/tmp/sonogym-pwned", "w"))


def test_checkpoints_never_unpickle_code(tmp_path):
    import os

    target = "/tmp/sonogym-pwned"
    if os.path.exists(target):
        os.remove(target)
    bad = tmp_path / "agent_5.pt"
    torch.save({"policy": {"w": torch.zeros(1)}, "x": _Payload()}, bad, pickle_module=pickle)
    with pytest.raises(CheckpointError, match="agent_5.pt"):
        read_checkpoint(bad)
    assert not os.path.exists(target)


def test_cli_refuses_bad_training_options_with_a_message(tmp_path):
    runner = CliRunner()
    for args, msg in (
        (["--steps", "0"], "--steps must be a positive integer"),
        (["--steps", "-5"], "--steps must be a positive integer"),
        (["--envs", "0"], "--envs must be a positive integer"),
        (["--obs-downsample", "0"], "--obs-downsample must be a positive integer"),
        (["--preset", "gpu"], "unknown preset"),
    ):
        res = runner.invoke(app, ["train", "--task", "navigation", "--out", str(tmp_path / "x"),
                                  *args])  # fmt: skip
        assert res.exit_code != 0 and msg in res.output, (args, res.output)
        assert not (tmp_path / "x" / "checkpoints").exists()


def test_malformed_run_config_is_named(run, tmp_path):
    import shutil

    r = tmp_path / "r"
    shutil.copytree(run, r)
    (r / "config.json").write_text("{not json")
    with pytest.raises(ValueError, match="config.json is not valid JSON"):
        evaluate_run(r, trials=1, envs=1)
    (r / "config.json").write_text(json.dumps({"task": "navigation"}))
    with pytest.raises(ValueError, match="lacks"):
        evaluate_run(r, trials=1, envs=1)


def test_a_second_run_into_a_folder_in_use_is_refused_naming_the_first(tmp_path, folder_in_use):
    out = tmp_path / "r"
    first = folder_in_use(out, "rl-run")  # a training run into out, still running
    for kw in ({}, {"force": True}):
        with pytest.raises(FileExistsError, match=rf"{out} is in use .*pid {first.pid}"):
            _tiny(out, seed=1, **kw)
    assert not (out / "config.json").exists() and not (out / "checkpoints").exists()


def test_force_replaces_only_a_marked_run_and_logs_what_it_deleted(run, tmp_path):
    import shutil

    from sonogym.runs import MARKER

    r = tmp_path / "r"
    shutil.copytree(run, r)
    logged = []
    _tiny(r, steps=8, force=True, log=logged.append)
    deleted = [m for m in logged if m.startswith("--force: deleted")]
    assert len(deleted) == 1 and "checkpoints/, config.json, events.out.tfevents" in deleted[0]
    (r / "notes.txt").write_text("my observations")
    with pytest.raises(FileExistsError, match="holds notes.txt, which sonogym train does not"):
        _tiny(r, steps=8, force=True)
    (r / "notes.txt").unlink()
    (r / MARKER).unlink()  # a run from before folders were marked
    with pytest.raises(FileExistsError, match="Delete it by hand"):
        _tiny(r, steps=8, force=True)
    assert (r / "checkpoints" / "agent_8.pt").is_file()
    assert _tiny(r, steps=16, resume=True).steps == 16  # resuming it still works


def test_eval_refuses_an_unwritable_run_before_running_and_writes_to_out(
    run, tmp_path, monkeypatch
):
    import shutil

    from sonogym.evaluation import rl_eval

    r = tmp_path / "r"
    shutil.copytree(run, r)
    (r / "episodes").write_text("")  # where the episode log goes cannot be a folder
    real = rl_eval.run_controllers
    monkeypatch.setattr(rl_eval, "run_controllers", lambda *a, **k: pytest.fail("ran episodes"))
    with pytest.raises(ValueError, match=rf"cannot write the evaluation into {r}.*--out"):
        evaluate_run(r, trials=2, envs=2, controllers=("policy",), plot=False)
    monkeypatch.setattr(rl_eval, "run_controllers", real)
    before = {p.name for p in r.iterdir()}
    res = CliRunner().invoke(app, ["eval", "--run", str(r), "--trials", "2", "--envs", "2",
                                   "--out", str(tmp_path / "ev")])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert {p.name for p in r.iterdir()} == before  # the run folder is untouched
    ev = tmp_path / "ev"
    assert (ev / "eval.json").is_file() and (ev / "eval.md").is_file()
    assert (ev / "episodes" / "idt.npz").is_file() and (ev / "trajectories-idt.png").is_file()


@pytest.mark.parametrize("task", ["../../escaped", "SonoGym/Navigation-v0", ["navigation"]])
def test_a_task_name_from_config_json_is_checked_against_the_registry(run, tmp_path, task):
    import shutil

    from sonogym.evaluation.curves import plot_curves
    from sonogym.evaluation.trained import load_run

    r = tmp_path / "runs" / "r"
    shutil.copytree(run, r)
    cfg = json.loads((r / "config.json").read_text())
    cfg["task"] = task
    (r / "config.json").write_text(json.dumps(cfg))
    for call in (
        lambda: load_run(r),
        lambda: evaluate_run(r, trials=1, envs=1, plot=False),
        lambda: plot_curves([r], tmp_path / "plots", expert=False),
        lambda: _tiny(r, steps=64, resume=True),
    ):
        with pytest.raises(ValueError, match=r"config.json: task .* is not a sonogym task"):
            call()
    # no file was written outside the run (none named after the task)
    assert [p for p in tmp_path.rglob("*") if p.is_file() and not p.is_relative_to(r)] == []


def test_progress_in_a_log_is_a_few_plain_lines(tmp_path, capsys):
    _tiny(tmp_path / "r", steps=200, progress=True, log=lambda m: None)
    err = capsys.readouterr().err
    assert "\r" not in err and err.endswith("\n")
    lines = err.splitlines()
    # a line every 5 % (or 30 s): 20 for 200 steps, where a tqdm bar writes an update every
    # few steps
    assert 10 <= len(lines) <= 25, err
    assert all(line.startswith("navigation/ppo: ") for line in lines)
    assert lines[-1].startswith("navigation/ppo: 200/200 step (100%)")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda c: c.update(task="bogus"), "task 'bogus' is not a sonogym task"),
        (lambda c: c.update(algo="dqn"), "unknown algorithm 'dqn'; known algorithms: ['ppo'"),
        (lambda c: c.update(algo="ppo-lag"), "algorithm 'ppo-lag' is not supported on navigation"),
        (lambda c: c.update(algo_params=[]), "algo_params must be an object"),
        (lambda c: c.update(seed="0"), "seed must be an integer, got '0'"),
        (lambda c: c.update(task_config=[]), "task_config must be an object"),
        (lambda c: c["task_config"].pop("env_kwargs"), "task_config lacks ['env_kwargs']"),
        (lambda c: c["task_config"]["env_kwargs"].update(w1="high"), "w1 must be a finite"),
        (lambda c: c["task_config"].update(obs_downsample=1.5), "obs_downsample must be an"),
        (lambda c: c["task_config"].update(net="huge"), "unknown net 'huge'"),
        (lambda c: c.update(obs_layout={"keys": ["_"]}), "obs_layout must hold 'keys'"),
        (lambda c: c["action_space"].update(low=[-1, -1]), "action_space.low must list 3"),
    ],
)
def test_a_hand_edited_run_config_is_named_before_an_env_is_built(
    run, tmp_path, monkeypatch, edit, message
):
    import shutil

    from sonogym.envs import registry

    r = tmp_path / "r"
    shutil.copytree(run, r)
    cfg = json.loads((r / "config.json").read_text())
    edit(cfg)
    (r / "config.json").write_text(json.dumps(cfg))

    def no_env(*a, **k):
        raise AssertionError("an env was built")

    monkeypatch.setattr(registry, "make_vec", no_env)
    with pytest.raises(ValueError) as e:
        evaluate_run(r, trials=1, envs=1)
    assert message in str(e.value) and str(r / "config.json") in str(e.value)
    res = CliRunner().invoke(app, ["eval", "--run", str(r), "--trials", "1"])
    assert res.exit_code != 0 and "restore" in " ".join(res.output.split())


def test_a_checkpoint_that_does_not_fit_the_edited_config_is_named(run, tmp_path):
    import shutil

    r = tmp_path / "r"
    shutil.copytree(run, r)
    cfg = json.loads((r / "config.json").read_text())
    cfg["obs_layout"]["shapes"] = [[s + 1 for s in sh] for sh in cfg["obs_layout"]["shapes"]]
    (r / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(CheckpointError, match="'policy' does not fit the network"):
        evaluate_run(r, trials=1, envs=1, controllers=("policy",), plot=False)
    # a config.json that asks for a module the checkpoint lacks (a ppo run's edited into a
    # ppo-sf one has no cost critic): named, not a KeyError
    from sonogym.agents.checkpoint import load_module

    with pytest.raises(CheckpointError, match="agent_32.pt holds no 'cost_critic'"):
        load_module(torch.nn.Linear(1, 1), r / "checkpoints" / "agent_32.pt", "cost_critic", "cpu")


def test_training_memory_that_does_not_fit_is_refused_before_the_agent_exists(
    tmp_path, monkeypatch
):
    import sonogym.memory
    from sonogym.agents.train import TRAINING_MEMORY_FACTOR
    from sonogym.memory import ResourceLimitError

    # the env fits (its own check reads the real free memory); training sees 1 MiB
    monkeypatch.setattr(sonogym.memory, "free_memory", lambda device: 2**20)
    with pytest.raises(ResourceLimitError) as e:
        _tiny(tmp_path / "r")
    need = TRAINING_MEMORY_FACTOR * 32 * 2 * (50 * 37) * 4  # rollouts x envs x obs x float32
    msg = str(e.value)
    assert "ppo training of 2 envs (32 rollout steps of 1850 observation floats" in msg
    assert f"{need / 2**30:.2f} GiB of memory" in msg and "fewer envs (--envs)" in msg
    assert not (tmp_path / "r" / "checkpoints").exists()
