"""Reports and learning curves from saved logs: the paper's columns and units, the same numbers
twice, pooling over seeds, and which runs each figure names. Runs here are synthetic (a
config.json, episode logs, TensorBoard scalars): the report reads nothing else."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest

from sonogym.envs.identity import IdentityMismatch, identity
from sonogym.envs.registry import get_task
from sonogym.evaluation.curves import curve_over_seeds, discover_runs, plot_curves
from sonogym.evaluation.episodes import EpisodeLog, episode_patient, load_log, log_path, save_log
from sonogym.evaluation.report import build_report, table1_columns, task_metrics
from sonogym.imitation.policies.registry import policy_for_algo
from sonogym.imitation.processor import PolicyFeatures
from sonogym.imitation.record import info_features
from sonogym.imitation.run import RUN_KIND as IL_KIND

TRIALS = 5
T = 6


def _metrics(task, rng, shift=0.0):
    keys = [m.key for m in task_metrics(task)] + ["return"]
    out = {k: (rng.random(TRIALS) * 10 + shift).astype(np.float32) for k in keys}
    if "safe_ratio" in out:
        out["safe_ratio"] = rng.random(TRIALS).astype(np.float32)
    return out


def _fake_run(root, task, algo, seed, simulator="physical", protocols=("idt",), curve=None):
    """A run folder as `sonogym train` + `sonogym eval` leave it (no checkpoints)."""
    run = Path(root) / f"{task}-{algo}-{simulator}-s{seed}"
    run.mkdir(parents=True)
    env = {"patients": [0, 1, 2, 3, 4], "simulator": simulator}
    if simulator == "learned":
        env["learned_nets"] = [0, 1, 2, 3]
    policy = policy_for_algo(algo)
    if policy is not None:  # an `sonogym il-train` run's config (no checkpoint to load)
        features = PolicyFeatures.from_info(info_features(task, len(get_task(task).action_names)))
        cfg = {
            "kind": IL_KIND, "task": task, "algo": algo, "seed": seed, "env_kwargs": env,
            "policy": policy.name, "policy_config": policy.config_cls.cpu().to_dict(),
            "train": {}, "features": features.to_dict(), "stats": {},
        }  # fmt: skip
    else:  # a `sonogym train` run's (the keys evaluation reads; no checkpoint to load)
        n_actions = len(get_task(task).action_names)
        cfg = {
            "task": task,
            "algo": algo,
            "seed": seed,
            "num_envs": 4,
            "obs_layout": {"keys": ["image"], "shapes": [[1, 50, 37]]},
            "action_space": {"low": [-1.0] * n_actions, "high": [1.0] * n_actions},
            "task_config": {"env_kwargs": env, "obs_downsample": 1, "obs_scales": {}},
            "algo_params": {},
        }
    cfg["identity"] = identity(task, env)
    (run / "config.json").write_text(json.dumps(cfg))
    rng = np.random.default_rng(hash((task, algo, seed, simulator)) % 2**32)
    track = get_task(task).track
    for proto in protocols:
        test_env = dict(env)
        if proto == "odt-patient":
            test_env["patients"] = [5]
        if proto == "odt-sim":
            test_env["learned_nets"] = [4]
        meta = {
            "task": task, "algo": algo, "run": run.name, "train_seed": seed, "protocol": proto,
            "eval_seed": 1000, "trials": TRIALS, "controllers": ["policy", "expert", "random"],
            "checkpoint": "agent_8.pt", "train_env": env, "test_env": test_env,
            "track_columns": list(track.columns), "track_units": list(track.units),
            "identity": identity(task, test_env), "train_identity": cfg["identity"],
        }  # fmt: skip
        exp_rng = np.random.default_rng(len(proto) + (simulator == "learned"))  # run-independent
        metrics = {
            "policy": _metrics(task, rng),
            "expert": _metrics(task, exp_rng, shift=100.0),
            "random": _metrics(task, rng),
        }
        if algo == "ppo-sf":  # sonogym eval adds the policy without its filter
            metrics["unfiltered"] = _metrics(task, rng)
        tracks = {c: rng.random((TRIALS, T + 1, len(track.columns))) for c in metrics}
        save_log(log_path(run, proto), meta, metrics, tracks)
    if curve is not None:
        from torch.utils.tensorboard import SummaryWriter

        w = SummaryWriter(str(run))
        for step, v in curve:
            w.add_scalar("Episode / return", v, step)
        w.close()
    return run


@pytest.fixture(scope="module")
def surgery_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("surgery-runs")
    runs = [
        _fake_run(root, "surgery", "ppo", 0, protocols=("idt", "odt-patient")),
        _fake_run(root, "surgery", "ppo", 1, protocols=("idt", "odt-patient")),
        _fake_run(root, "surgery", "ppo-sf", 0, protocols=("idt", "odt-patient")),
        _fake_run(
            root, "surgery", "ppo", 0, "learned", protocols=("idt", "odt-sim", "odt-patient")
        ),
        _fake_run(root, "surgery", "act", 0, "learned", protocols=("idt",)),  # an IL run
        _fake_run(root, "navigation", "ppo", 0),  # another task: left out
    ]
    return root, runs


def test_table1_columns_are_the_papers_metrics_and_units():
    cols = [(m.label, m.unit, col) for m, col in table1_columns()]
    assert cols == [
        (label, unit, col)
        for label, unit in (
            ("side err", "mm"),
            ("insert err", "mm"),
            ("rot err", "deg"),
            ("safe ratio", "%"),
        )  # fmt: skip
        for col in ("IDT", "ODT")
    ]
    keys = [m.key for m in task_metrics("surgery")]
    assert keys == ["side_error_mm", "insertion_error_mm", "rotation_error_deg", "safe_ratio"]
    for task in ("navigation", "reconstruction", "surgery"):  # names the env reports
        assert {m.key for m in task_metrics(task)} == _reported_metrics(task)


def _reported_metrics(task: str) -> set[str]:
    """The metric names an episode of ``task`` ends with (one-step episodes)."""
    import torch

    from sonogym.envs.registry import make_vec

    env = make_vec(task, 1, obs_mode="state", phantom_spacing=0.002, episode_length=1)
    env.reset(seed=0)
    _, _, _, _, info = env.step(torch.zeros(1, *env.single_action_space.shape))
    return set(info["final_info"]) - {"env_ids", "return"}


def test_surgery_report_is_reproducible_and_pools_the_right_logs(surgery_runs, tmp_path):
    root, runs = surgery_runs
    a = build_report("surgery", [root], tmp_path / "a", curves=False)
    b = build_report("surgery", [root], tmp_path / "b", curves=False)
    files = sorted(p.name for p in a.parent.iterdir())
    assert files == ["identity.json", "metrics.csv", "report.md", "table1.csv", "table1.md"]
    for name in files:  # same logs, same numbers, byte for byte
        assert (a.parent / name).read_bytes() == (b.parent / name).read_bytes(), name

    rows = list(csv.DictReader(io.StringIO((a.parent / "table1.csv").read_text())))
    assert [(r["us_sim"], r["algos"]) for r in rows] == [
        ("MB", "PPO"), ("MB", "PPO + SF"), ("MB", "PPO + SF, filter off"), ("MB", "expert"),
        ("LB", "PPO"), ("LB", "ACT"), ("LB", "expert"),
    ]  # fmt: skip
    mb_ppo, lb_act = rows[0], rows[5]
    # the ppo-sf run's unfiltered episodes make their own row, not the PPO + SF one
    off = load_log(log_path(runs[2], "idt")).metrics["unfiltered"]["side_error_mm"]
    assert float(rows[2]["side_error_mm_IDT_mean"]) == pytest.approx(
        float(off.astype(np.float64).mean()), rel=1e-5
    )
    assert int(rows[1]["side_error_mm_IDT_n"]) == int(rows[2]["side_error_mm_IDT_n"]) == TRIALS
    # MB PPO pools both seeds' episodes; IDT from idt logs, ODT from odt-patient logs
    for col, proto in (("IDT", "idt"), ("ODT", "odt-patient")):
        v = np.concatenate(
            [load_log(log_path(r, proto)).metrics["policy"]["side_error_mm"] for r in runs[:2]]
        ).astype(np.float64)
        assert int(mb_ppo[f"side_error_mm_{col}_n"]) == 2 * TRIALS
        assert float(mb_ppo[f"side_error_mm_{col}_mean"]) == pytest.approx(v.mean(), rel=1e-5)
        assert float(mb_ppo[f"side_error_mm_{col}_std"]) == pytest.approx(v.std(ddof=1), rel=1e-5)
    # safe ratio in percent
    sr = load_log(log_path(runs[0], "idt")).metrics["policy"]["safe_ratio"]
    sr1 = load_log(log_path(runs[1], "idt")).metrics["policy"]["safe_ratio"]
    want = 100 * np.concatenate([sr, sr1]).astype(np.float64).mean()
    assert float(mb_ppo["safe_ratio_IDT_mean"]) == pytest.approx(want, rel=1e-5)
    # LB's ODT column is the odt-sim log; an IL run without ODT logs leaves it empty
    lb_ppo = rows[4]
    v = load_log(log_path(runs[3], "odt-sim")).metrics["policy"]["rotation_error_deg"]
    assert float(lb_ppo["rotation_error_deg_ODT_mean"]) == pytest.approx(float(v.mean()), rel=1e-5)
    assert lb_act["side_error_mm_IDT_n"] == str(TRIALS) and lb_act["side_error_mm_ODT_n"] == ""
    # the expert does not depend on the run: its MB episodes count once, not three times
    assert rows[3]["side_error_mm_IDT_n"] == str(TRIALS)
    md = a.read_text()
    assert "surgery-ppo-physical-s1 (seed 1)" in md and "navigation" not in md.split("Runs:")[1]
    assert "| MB | PPO + SF | 2.17 | 8.94 |" in md  # the paper's values beside ours
    assert "side err [mm] IDT | side err [mm] ODT" in (a.parent / "table1.md").read_text()
    # LB runs on the held-out patient: the appendix's "new patient" table, beside the paper's
    new = md.split("## New patient")[1]
    v = load_log(log_path(runs[3], "odt-patient")).metrics["policy"]["insertion_error_mm"]
    assert (
        f"{float(v.astype(np.float64).mean()):.3g} ±" in new and "| PPO + SF | 17.6 ± 54.2" in new
    )


def test_learning_curves_over_seeds_with_the_expert_line(tmp_path):
    root = tmp_path / "runs"
    r0 = _fake_run(root, "navigation", "ppo", 0, curve=[(10, 1.0), (20, 2.0), (30, 3.0)])
    r1 = _fake_run(root, "navigation", "ppo", 1, curve=[(10, 3.0), (20, 4.0)])
    c = curve_over_seeds([r0, r1])
    # common range 40..80 env steps (per-env step x 4 envs); mean and std over the two seeds
    assert c.steps[0] == 40 and c.steps[-1] == 80 and c.seeds == [0, 1]
    np.testing.assert_allclose(c.mean[[0, -1]], [2.0, 3.0])
    np.testing.assert_allclose(c.std[[0, -1]], [1.0, 1.0])

    from typer.testing import CliRunner

    from sonogym.cli import app

    out = tmp_path / "plots"
    res = CliRunner().invoke(app, ["plot", "--runs", str(r0), str(r1), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert (out / "curves-navigation-episode_return.png").stat().st_size > 0
    rows = list(csv.reader(io.StringIO((out / "curves-navigation-episode_return.csv").read_text())))
    expert = [r for r in rows if r[1] == "expert"]
    exp_mean = np.mean(
        [load_log(log_path(r, "idt")).metrics["expert"]["return"].astype(np.float64).mean()
         for r in (r0, r1)]
    )  # fmt: skip
    assert len(expert) == 1 and float(expert[0][5]) == pytest.approx(exp_mean, rel=1e-5)
    md = (out / "curves.md").read_text()
    assert "navigation-ppo-physical-s0 (seed 0), navigation-ppo-physical-s1 (seed 1)" in md
    assert discover_runs([root]) == [r0, r1]
    assert plot_curves([r0], tmp_path / "none", metrics=("Loss / missing",)) == []


def test_navigation_report_draws_the_bar_chart_and_curves(tmp_path):
    root = tmp_path / "runs"
    for seed in (0, 1):
        _fake_run(root, "navigation", "ppo", seed, protocols=("idt",), curve=[(1, 0.0), (2, 1.0)])
    _fake_run(root, "navigation", "ppo", 0, "learned", protocols=("idt", "odt-sim"))
    md = build_report("navigation", [root], tmp_path / "rep")
    names = {p.name for p in md.parent.iterdir()}
    assert {"bars.png", "metrics.csv", "curves-navigation-episode_return.png"} <= names
    rows = list(csv.DictReader(io.StringIO((md.parent / "metrics.csv").read_text())))
    groups = {(r["sim"], r["protocol"]) for r in rows}
    assert groups == {("MB", "idt"), ("LB", "idt"), ("LB", "odt-sim")}
    assert {r["unit"] for r in rows if r["metric"] == "angle_error_deg"} == {"deg"}
    assert "navigation-ppo-learned-s0 (seed 0)" in md.read_text()
    with pytest.raises(FileNotFoundError, match="no reconstruction runs"):
        build_report("reconstruction", [root], tmp_path / "x")


def test_policies_trained_on_the_privileged_state_are_named_so():
    from sonogym.evaluation.report import _method

    meta = {"task": "surgery", "algo": "ppo", "train_env": {"obs_mode": "state"}}
    assert _method("policy", meta) == "PPO (state)"
    assert _method("policy", {**meta, "train_env": {}}) == "PPO"
    assert _method("unfiltered", {**meta, "algo": "ppo-sf"}) == "PPO + SF (state), filter off"


def test_the_episode_patient_follows_the_evaluation_envs():
    def log(patients, num_envs):
        meta = {"task": "navigation", "test_env": {"patients": patients}}
        if num_envs is not None:
            meta["num_envs"] = num_envs
        return EpisodeLog(Path("x.npz"), meta, {}, {})

    # episode k ran in env k % num_envs, which holds patient (env % P)
    assert [episode_patient(log([3, 7], 2), k) for k in range(4)] == [3, 7, 3, 7]
    assert [episode_patient(log([3, 7, 9], 2), k) for k in range(4)] == [3, 7, 3, 7]
    assert [episode_patient(log([3, 7], 4), k) for k in range(4)] == [3, 7, 3, 7]
    assert [episode_patient(log([3, 7, 9], 4), k) for k in range(5)] == [3, 7, 9, 3, 3]
    assert episode_patient(log(["/data/s1"], None), 5) == "/data/s1"
    assert episode_patient(EpisodeLog(Path("x"), {"task": "surgery"}, {}, {}), 2) == 0
    with pytest.raises(ValueError, match="evaluate the run again"):
        episode_patient(log([3, 7], None), 1)


def _set_identity(run: Path, **change) -> None:
    cfg = json.loads((run / "config.json").read_text())
    cfg["identity"] = {**cfg["identity"], **change}
    (run / "config.json").write_text(json.dumps(cfg))


def test_report_and_plot_stamp_the_identity_and_refuse_a_run_of_another(tmp_path):
    curve = [(10, 1.0), (20, 2.0)]
    runs = [_fake_run(tmp_path / "runs", "navigation", "ppo", s, curve=curve) for s in (0, 1)]
    md = build_report("navigation", runs, tmp_path / "report", curves=False).read_text()
    assert "benchmark identity: generator v" in md and "navigation task v2" in md
    assert json.loads((tmp_path / "report" / "identity.json").read_text())["task_version"] == 2
    plot_curves(runs, tmp_path / "plot")
    assert "navigation task v2" in (tmp_path / "plot" / "curves.md").read_text()

    _set_identity(runs[1], task_version=1)
    with pytest.raises(IdentityMismatch, match=f"{runs[1].name} .*task_version 1, not 2"):
        build_report("navigation", runs, tmp_path / "report2", curves=False)
    assert not (tmp_path / "report2").exists()  # refused before anything is written
    with pytest.raises(IdentityMismatch, match=runs[1].name):
        plot_curves(runs, tmp_path / "plot2")
    assert not (tmp_path / "plot2").exists()
