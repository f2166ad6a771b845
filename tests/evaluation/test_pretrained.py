"""Shipped policies: a run exported as a pretrained policy (config, safetensors weights, model
card) acts exactly as the run's own checkpoint, and ``sonogym eval --pretrained`` evaluates it
like a run, writing the same files to --out."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sonogym.cli import app
from sonogym.evaluation import pretrained as P


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "nav"
    args = ["train", "--task", "navigation", "--obs-mode", "us_heading", "--steps", "64",
            "--envs", "4", "--phantom-spacing", "2", "--env-option", "episode_length=50",
            "--checkpoint-every", "32", "--out", str(out)]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return out


def test_training_records_checkpoints_and_their_cpu_time(tiny_run):
    from sonogym.agents.checkpoint import RL_RUN
    from sonogym.agents.train import read_times
    from sonogym.runs import RunFolder

    steps = [t for t, _ in RunFolder(tiny_run, RL_RUN).checkpoints()]
    assert sorted(steps) == [0, 32, 64]  # --checkpoint-every 32
    times = read_times(tiny_run / "checkpoints")
    assert sorted(times) == [32, 64]
    assert 0 < times[32]["cpu_s"] <= times[64]["cpu_s"] and times[64]["wall_s"] > 0


def test_exported_weights_act_as_the_checkpoint(tiny_run, tmp_path):
    from sonogym.agents.checkpoint import RL_RUN, read_checkpoint
    from sonogym.runs import RunFolder

    ckpt = RunFolder(tiny_run, RL_RUN).require_checkpoint().path
    dest = P.export_pretrained(tiny_run, "nav-test", root=tmp_path, notes="a test")
    assert P.available(tmp_path) == ["nav-test"]
    a, b = read_checkpoint(ckpt), read_checkpoint(dest / P.WEIGHTS)
    assert set(b) == {"policy"}  # acting modules only: no value net, no optimiser
    assert set(a["policy"]) == set(b["policy"])
    assert all(torch.equal(a["policy"][k], b["policy"][k]) for k in a["policy"])
    card = P.read_card("nav-test", tmp_path)
    assert card["task"] == "navigation" and card["steps_per_env"] == 64
    assert card["steps_total"] == 64 * 4 and card["cpu_minutes"] is not None
    assert "a test" in (dest / "model_card.md").read_text()


def test_the_card_lists_only_evaluations_of_the_exported_checkpoint(tiny_run, tmp_path):
    rows = {"policy": {"position_error_mm": [3.0, 1.0]}}
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    for stem, ckpt in (("eval", "agent_64.pt"), ("eval-old", "agent_32.pt")):
        table = {"protocol": stem, "trials": 4, "seed": 7, "num_envs": 3, "checkpoint": ckpt,
                 "results": rows}  # fmt: skip
        (run / f"{stem}.json").write_text(json.dumps(table))
    dest = P.export_pretrained(run, "nav-test", root=tmp_path / "shipped")
    card = P.read_card("nav-test", tmp_path / "shipped")
    assert list(card["evaluations"]) == ["eval"] and card["checkpoint"] == "agent_64.pt"
    # the card says how to draw the same starts again: trials, seed and env count
    assert card["evaluations"]["eval"]["seed"] == 7 and card["evaluations"]["eval"]["num_envs"] == 3
    assert (
        "### eval (4 episodes, seed 7, 3 envs, checkpoint agent_64.pt)"
        in (dest / "model_card.md").read_text()
    )
    P.export_pretrained(
        run, "nav-old", root=tmp_path / "shipped", checkpoint=run / "checkpoints" / "agent_32.pt"
    )
    assert list(P.read_card("nav-old", tmp_path / "shipped")["evaluations"]) == ["eval-old"]


def test_eval_pretrained_writes_a_runs_table_to_out(tiny_run, tmp_path, monkeypatch):
    P.export_pretrained(tiny_run, "nav-test", root=tmp_path / "shipped")
    monkeypatch.setattr(P, "PRETRAINED_DIR", tmp_path / "shipped")
    runner = CliRunner()
    listed = runner.invoke(app, ["eval", "--pretrained", "list"])
    assert listed.exit_code == 0 and listed.output.startswith("nav-test: navigation ppo")
    out = tmp_path / "eval"
    res = runner.invoke(app, ["eval", "--pretrained", "nav-test", "--trials", "2", "--envs", "2",
                              "--out", str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    table = json.loads((out / "eval.json").read_text())
    assert table["checkpoint"] == P.WEIGHTS and set(table["results"]) >= {"policy", "expert"}
    assert (table["trials"], table["seed"], table["num_envs"]) == (2, 1000, 2)
    assert (out / "episodes" / "idt.npz").is_file()
    # the same evaluation of the run's own checkpoint gives the same figures
    same = runner.invoke(app, ["eval", "--run", str(tiny_run), "--trials", "2", "--envs", "2",
                               "--out", str(tmp_path / "run-eval")])  # fmt: skip
    assert same.exit_code == 0, same.output
    ref = json.loads((tmp_path / "run-eval" / "eval.json").read_text())
    assert ref["results"]["policy"] == table["results"]["policy"]
    bad = runner.invoke(app, ["eval", "--pretrained", "nope"])
    assert bad.exit_code != 0 and "ships ['nav-test']" in str(bad.output)


def test_demo_runs_a_shipped_policy_beside_the_expert(tiny_run, tmp_path, monkeypatch):
    from sonogym.envs.registry import make_vec
    from sonogym.evaluation import demo

    dest = P.export_pretrained(tiny_run, "nav-test", root=tmp_path / "shipped")
    cfg = json.loads((dest / "config.json").read_text())
    cfg["task_config"]["env_kwargs"]["patients"] = [7, 8]  # trained on another cohort
    (dest / "config.json").write_text(json.dumps(cfg))
    monkeypatch.setattr(P, "PRETRAINED_DIR", tmp_path / "shipped")
    small = {"phantom_spacing": 0.002, "episode_length": 20}
    built = []

    def small_env(t, n, **kw):
        built.append(kw.get("patients"))
        return make_vec(t, n, **{**small, **kw})

    monkeypatch.setattr(demo, "make_vec", small_env)
    results = demo.run_demo(tmp_path / "demo", num_envs=2, tasks=("navigation",), log=print)
    assert built == [None, (0,)]  # its card reports no test patients: the expert's phantom 0
    assert set(results) == {"navigation", "navigation_pretrained-nav-test"}
    shipped = results["navigation_pretrained-nav-test"]
    assert shipped["controller"] == "pretrained nav-test"
    assert "position_error_mm" in shipped["metrics"]
    assert (tmp_path / "demo" / "navigation_pretrained-nav-test.mp4").stat().st_size > 0
    assert (
        "| navigation | pretrained nav-test | position_error_mm |"
        in (tmp_path / "demo" / "metrics.md").read_text()
    )


def test_the_demo_shows_the_shipped_navigation_policy_as_its_model_card_does(tmp_path):
    from sonogym.evaluation import demo

    results = demo.run_demo(tmp_path / "demo", num_envs=1, tasks=("navigation",), log=print)
    shown = results["navigation_pretrained-navigation"]
    card = shown["model_card"]
    # a fair sample: the card's own test patients (held out from training), 16 starts
    assert shown["patients"] == [str(p) for p in card["patients"]]
    assert shown["envs"] == demo.POLICY_EPISODES
    mean, _ = shown["metrics"]["position_error_mm"]
    card_mean, card_std = card["metrics"]["position_error_mm"]
    assert abs(mean - card_mean) <= card_std, (mean, card_mean, card_std)
    assert "model card (odt-patient" in (tmp_path / "demo" / "metrics.md").read_text()


def test_the_shipped_navigation_policy_loads_weights_only_and_acts():
    from sonogym.agents.checkpoint import acting_modules, load_policy, read_checkpoint

    assert "navigation" in P.available()
    weights = read_checkpoint(P.weights("navigation"))  # safetensors: tensors, nothing unpickled
    model, cfg = load_policy(P.pretrained_dir("navigation"), P.weights("navigation"))
    assert set(weights) <= set(acting_modules(cfg["algo"])) and "policy" in weights
    assert cfg["task"] == "navigation"
    width = sum(int(np.prod(s)) for s in cfg["obs_layout"]["shapes"])
    obs = torch.rand(3, width, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        act = model.act({"observations": obs}, role="policy")[1]["mean_actions"]
    assert act.shape == (3, len(cfg["action_space"]["low"])) and torch.isfinite(act).all()
    card = P.read_card("navigation")
    assert card["training_patients"] == list(range(100, 164))  # phantoms only (no held-out seed)
    assert {"odt-patient", "real-subject"} <= set(card["evaluations"])


def test_select_picks_the_best_checkpoint_on_its_patients_and_export_ships_it(tiny_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    args = ["select", "--run", str(run), "--patients", "3", "--trials", "4", "--envs", "4",
            "--checkpoint", str(run / "checkpoints" / "agent_0.pt"),
            "--checkpoint", str(run / "checkpoints" / "agent_64.pt")]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    sel = json.loads((run / "selection.json").read_text())
    assert sel["metric"] == "position_error_mm" and sel["patients"] == ["3"]
    means = {r["checkpoint"]: r["results"]["position_error_mm"][0] for r in sel["checkpoints"]}
    assert sorted(means) == ["agent_0.pt", "agent_64.pt"]
    assert sel["selected"] == min(means, key=means.get)
    # each checkpoint's evaluation is kept apart from the run's own, on the selection patient
    table = json.loads((run / "selection" / "eval-step-64.json").read_text())
    assert table["checkpoint"] == "agent_64.pt" and table["env_overrides"]["patients"] == [3]
    assert not list(run.glob("eval*.json"))

    # export ships the selected checkpoint by default, and its card says how it was chosen
    P.export_pretrained(run, "nav-sel", root=tmp_path / "shipped")
    card = P.read_card("nav-sel", tmp_path / "shipped")
    assert card["checkpoint"] == sel["selected"]
    assert card["selection"]["patients"] == ["3"] and card["selection"]["trials"] == 4
    # `eval --checkpoint selected` evaluates the chosen one
    args = ["eval", "--run", str(run), "--checkpoint", "selected", "--trials", "2", "--envs", "2",
            "--controllers", "policy", "--patients", "4", "--name", "sel"]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert json.loads((run / "eval-sel.json").read_text())["checkpoint"] == sel["selected"]
    # an evaluation of that checkpoint on a selection patient is not a test: refused
    leak = {"protocol": "custom", "trials": 4, "seed": 1, "checkpoint": sel["selected"],
            "env_overrides": {"patients": [3]}, "results": {}}  # fmt: skip
    (run / "eval-custom.json").write_text(json.dumps(leak))
    with pytest.raises(ValueError, match="selected on patients"):
        P.export_pretrained(run, "nav-sel2", root=tmp_path / "shipped")
    assert not (tmp_path / "shipped" / "nav-sel2").exists()


def test_select_refuses_an_unknown_metric(tiny_run):
    res = CliRunner().invoke(
        app, ["select", "--run", str(tiny_run), "--patients", "3", "--metric", "coverage"]
    )
    assert res.exit_code != 0 and "no metric 'coverage'" in res.output
