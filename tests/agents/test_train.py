"""Tiny training runs: weights change, checkpoints load, configs resolve, refusals are clear."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from sonogym.agents.algorithms import algo_config, check_algo, task_algorithms
from sonogym.agents.checkpoint import load_policy
from sonogym.agents.configs import task_config
from sonogym.agents.train import train
from sonogym.envs.identity import identity

FAST_ENV = dict(phantom_spacing=0.002)


def _tiny(task, algo, out, steps, env_kwargs_extra=None, **kw):
    torch.set_num_threads(1)
    return train(
        task,
        algo,
        envs=2,
        steps=steps,
        seed=0,
        out=out,
        patients=(0,),
        obs_downsample=2 if task == "navigation" else 1,
        env_kwargs=dict(FAST_ENV, episode_length=20, **(env_kwargs_extra or {})),
        **{"progress": False, **kw},
    )


def _weights_changed(run, t):
    first = torch.load(run / "checkpoints" / "agent_0.pt", weights_only=False)["policy"]
    last = torch.load(run / "checkpoints" / f"agent_{t}.pt", weights_only=False)["policy"]
    assert first.keys() == last.keys()
    changed = [k for k in first if not torch.equal(first[k], last[k])]
    # the shared encoder and both heads moved
    assert any(k.startswith("encoder.branches") for k in changed)
    assert "mean_head.weight" in changed and "value_head.weight" in changed
    return changed


def test_navigation_ppo_trains_logs_checkpoints_and_resumes(tmp_path):
    run = tmp_path / "nav"
    res = _tiny("navigation", "ppo", run, steps=64)
    assert res.checkpoint == run / "checkpoints" / "agent_64.pt" and res.checkpoint.exists()
    _weights_changed(run, 64)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["algo_params"]["rollouts"] == 32
    assert cfg["algo_params"]["time_limit_bootstrap"] is True
    assert "ppo" not in cfg["task_config"]  # a run records its own algorithm's config only
    assert cfg["task_config"]["obs_downsample"] == 2 and cfg["num_envs"] == 2
    assert cfg["task_config"]["env_kwargs"]["patients"] == [0]
    assert cfg["identity"] == identity("navigation", cfg["task_config"]["env_kwargs"])
    events = list(run.glob("events.out.tfevents.*"))
    assert events and events[0].stat().st_size > 0

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    assert "Loss / Policy loss" in tags and "Episode / position_error_mm" in tags

    policy, loaded_cfg = load_policy(run)
    assert loaded_cfg["task"] == "navigation"
    x = torch.rand(3, policy.encoder.layout.size)
    _, out = policy.act({"observations": x}, role="policy")
    assert out["mean_actions"].shape == (3, 3)
    saved = torch.load(res.checkpoint, weights_only=False)["policy"]
    assert torch.equal(policy.mean_head.weight, saved["mean_head.weight"])

    with pytest.raises(FileExistsError, match="resume"):
        _tiny("navigation", "ppo", run, steps=96)
    # optimisers step all tensors at once (foreach), also after resuming a checkpoint saved
    # without it (load_state_dict restores the saved flag)
    state = torch.load(res.checkpoint, weights_only=False)
    assert all(g["foreach"] is True for g in state["optimizer"]["param_groups"])
    for g in state["optimizer"]["param_groups"]:
        g["foreach"] = None
    torch.save(state, res.checkpoint)
    res2 = _tiny("navigation", "ppo", run, steps=96, resume=True)
    assert res2.checkpoint.name == "agent_96.pt"
    state = torch.load(res2.checkpoint, weights_only=False)
    assert all(g["foreach"] is True for g in state["optimizer"]["param_groups"])
    assert json.loads((run / "config.json").read_text())["resumed_from"] == 64
    with pytest.raises(ValueError, match="cannot resume"):
        _tiny("navigation", "a2c", run, steps=128, resume=True)
    # a run trained under another benchmark identity is not continued under this one
    cfg = json.loads((run / "config.json").read_text())
    cfg["identity"]["task_version"] = 1
    (run / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="another benchmark identity.*navigation task v1"):
        _tiny("navigation", "ppo", run, steps=128, resume=True)


def test_navigation_with_heading_trains_an_image_branch_and_a_heading_branch(tmp_path):
    """obs_mode="us_heading": the Dict observation reaches the encoder as a conv branch over the
    pooled image and an MLP over the heading, and the trained policy's action reads both."""
    run = tmp_path / "nav-heading"
    _tiny(
        "navigation", "ppo", run, steps=32, net="small", env_kwargs_extra={"obs_mode": "us_heading"}
    )
    policy, cfg = load_policy(run)
    layout = policy.encoder.layout
    assert layout.keys == ("heading", "image") and layout.shapes == ((2,), (1, 100, 75))
    assert isinstance(policy.encoder.branches["heading"][0], torch.nn.Linear)
    x = torch.rand(4, layout.size)
    mean = policy.act({"observations": x}, role="policy")[1]["mean_actions"]
    x_flipped = x.clone()
    x_flipped[:, :2] = -x_flipped[:, :2]  # heading first (sorted keys): the probe turned 180 deg
    mean_flipped = policy.act({"observations": x_flipped}, role="policy")[1]["mean_actions"]
    assert not torch.allclose(mean, mean_flipped)


@pytest.mark.parametrize(
    "task,algo,steps,net",
    [
        ("navigation", "a2c", 32, "small"),
        ("reconstruction", "ppo", 32, "paper"),
        ("reconstruction", "a2c", 64, "small"),
        ("surgery", "ppo", 32, "paper"),
        ("surgery", "a2c", 64, "paper"),
    ],
)
def test_every_pair_updates_weights(tmp_path, task, algo, steps, net):
    res = _tiny(task, algo, tmp_path / f"{task}-{algo}", steps=steps, net=net)
    assert res.checkpoint.exists()
    _weights_changed(res.out, steps)
    policy, cfg = load_policy(res.out)
    assert cfg["task_config"]["net"] == net
    assert policy.mean_head.out_features == {"reconstruction": 4, "surgery": 6}.get(task, 3)
    # the loaded trunk is the one trained (small: 16 channels in the first conv, paper: 32)
    first_conv = next(m for m in policy.encoder.modules() if isinstance(m, torch.nn.Conv2d))
    assert first_conv.out_channels == {"small": 16, "paper": 32}[net]


def test_unsupported_pairs_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"supported: \['ppo', 'a2c'\]"):
        check_algo("navigation", "ppo-lag")
    with pytest.raises(ValueError, match="known tasks"):
        check_algo("nope", "ppo")
    assert task_algorithms("surgery") == ("ppo", "a2c", "ppo-sf", "ppo-lag")
    with pytest.raises(ValueError, match="not supported on reconstruction"):
        _tiny("reconstruction", "ppo-sf", tmp_path / "sf", steps=16)


def test_paper_hyperparameters():
    tasks = ("navigation", "reconstruction", "surgery")
    nav, rec, sur = (algo_config(t, "ppo") for t in tasks)
    assert (nav.rollouts, nav.learning_epochs, nav.mini_batches) == (32, 5, 32)
    assert (rec.rollouts, rec.learning_epochs, rec.mini_batches) == (32, 3, 4)
    assert (sur.rollouts, sur.learning_epochs, sur.mini_batches) == (16, 3, 32)
    assert (nav.learning_rate, rec.learning_rate, sur.learning_rate) == (1e-4, 3e-4, 1e-4)
    assert (nav.value_clip, rec.value_clip, sur.value_clip) == (0.2, 0.1, 0.1)
    a2c = [algo_config(t, "a2c") for t in tasks]
    assert [(c.rollouts, c.mini_batches) for c in a2c] == [(16, 32), (64, 32), (64, 4)]
    for c, a in zip((nav, rec, sur), a2c, strict=True):
        assert c.kl_threshold == 0.008 == a.kl_threshold
        assert c.grad_norm_clip == 1.0 and c.ratio_clip == 0.2
    assert all(task_config(t).num_envs == 128 for t in tasks)
    # the safe-RL algorithms train on the task's PPO table, with the reference's settings
    sf, lag = algo_config("surgery", "ppo-sf"), algo_config("surgery", "ppo-lag")
    assert sf.learning_rate == lag.learning_rate == sur.learning_rate
    assert (sf.cost_threshold, sf.filter_mode, lag.cost_limit) == (0.5, "search", 5.0)


def test_cli_train_and_refusal(tmp_path):
    from typer.testing import CliRunner

    from sonogym.cli import app

    runner = CliRunner()
    bad = runner.invoke(app, ["train", "--task", "navigation", "--algo", "ppo-sf"])
    flat = "".join(c for c in bad.output if c.isalnum() or c in "[]',:-")
    assert bad.exit_code != 0 and "supported:['ppo','a2c']" in flat
    out = tmp_path / "cli"
    args = ["train", "--task", "surgery", "--algo", "ppo", "--envs", "2", "--steps", "16"]
    args += ["--patients", "0", "--phantom-spacing", "2", "--out", str(out)]
    args += ["--env-option", "unsafe_penalty=0.5", "--env-option", "w5=20"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert (out / "checkpoints" / "agent_16.pt").exists()
    assert json.loads((out / "config.json").read_text())["task_config"]["env_kwargs"] == {
        "patients": [0],
        "phantom_spacing": 0.002,
        # --env-option overrides the cpu preset's w5 = 50 and adds its own beside the preset's
        # distance penalty and action box; recorded for eval and resume
        "w5": 20,
        "unsafe_distance_penalty": 100.0,
        "action_limit": [0.005, 0.005, 0.01, 0.02, 0.02, 0.001],
        "unsafe_penalty": 0.5,
    }


@pytest.mark.parametrize(
    ("option", "message"),
    [
        ("bogus=1", "surgery has no such option"),
        ("obs_mode=state", "use --obs-mode"),
        ("unsafe_penalty", "write KEY=VALUE"),
        ("unsafe_penalty=high", "expected a number"),
        # what trained to NaN weights or was truncated in silence
        ("w5=nan", "--env-option w5=nan: SurgeryConfig.w5 must be a finite number"),
        ("w5=inf", "SurgeryConfig.w5 must be a finite number"),
        ("w5=1e309", "--env-option w5=1e309: SurgeryConfig.w5 must be a finite number"),
        ("episode_length=2.5", "SurgeryConfig.episode_length must be an integer, got 2.5"),
        ("episode_length=1e309", "SurgeryConfig.episode_length must be an integer"),
        ("action_scale=0.1,0.1,nan,1,1,1", "SurgeryConfig.action_scale[2] must be a finite"),
        ("corridor_damping=0", "corridor_damping must be in (0, 1]"),  # the config's own range
    ],
)
def test_cli_env_option_refusals(option, message, tmp_path):
    """A bad --env-option is refused before anything is built or written, naming the fix."""
    from typer.testing import CliRunner

    from sonogym.cli import app

    out = tmp_path / "never"
    args = ["train", "--task", "surgery", "--env-option", option, "--out", str(out)]
    res = CliRunner().invoke(app, args)
    flat = " ".join(res.output.replace("│", " ").split())
    assert res.exit_code != 0 and message in flat, res.output
    assert not out.exists()


def test_env_option_values_follow_the_option_type():
    from typer import BadParameter

    from sonogym.cli import parse_env_options

    items = ["action_scale=0.004,0.004,0.05,1,1,1", "corridor_damping=1"]
    got = parse_env_options("surgery", items)
    assert got == {"action_scale": (0.004, 0.004, 0.05, 1, 1, 1), "corridor_damping": 1}
    with pytest.raises(BadParameter, match="action_scale needs 6 positive values"):
        parse_env_options("surgery", ["action_scale=0.004,0.004,0.05"])  # surgery has 6
    got = parse_env_options("surgery", ["episode_length=20.0"])  # an integral float: 20
    assert got == {"episode_length": 20} and type(got["episode_length"]) is int


def test_init_from_starts_from_the_checkpoint_and_counts_its_cost(tmp_path):
    """A fine-tuning run starts from another run's weights and value statistics (not its
    optimiser), takes its own settings, and its times.json counts the source run's CPU time."""
    from sonogym.agents.train import read_times

    src = tmp_path / "src"
    _tiny("navigation", "ppo", src, steps=64, checkpoint_interval=32)
    ckpt = src / "checkpoints" / "agent_32.pt"
    source_cpu = read_times(src / "checkpoints")[32]["cpu_s"]
    assert source_cpu > 0
    tuned = tmp_path / "tuned"
    settings = {"final_log_std": -1.0, "anneal_steps": 32, "ppo.learning_rate": 3e-5}
    _tiny("navigation", "ppo", tuned, steps=32, settings=settings, init_from=ckpt)
    start = torch.load(tuned / "checkpoints" / "agent_0.pt", weights_only=True)
    source = torch.load(ckpt, weights_only=True)
    for name in ("policy", "value_preprocessor"):
        assert start[name].keys() == source[name].keys()
        assert all(torch.equal(start[name][k], source[name][k]) for k in source[name])
    # a fresh Adam: no moments carried over, the new run's learning rate
    assert start["optimizer"]["state"] == {}
    assert start["optimizer"]["param_groups"][0]["lr"] == pytest.approx(3e-5)
    cfg = json.loads((tuned / "config.json").read_text())
    assert cfg["init_from"]["checkpoint"] == str(ckpt.resolve())
    assert cfg["init_from"]["steps"] == 32 and cfg["init_from"]["cpu_s"] == source_cpu
    assert cfg["task_config"]["learning"]["final_log_std"] == -1.0
    assert cfg["algo_params"]["learning_rate"] == pytest.approx(3e-5)
    assert read_times(tuned / "checkpoints")[32]["cpu_s"] > source_cpu
    # the run's own exploration schedule: its sigma ceiling has fallen to exp(-1)
    policy, _ = load_policy(tuned)
    assert float(policy.log_std_max) == pytest.approx(-1.0)


def test_init_from_refuses_what_cannot_continue(tmp_path):
    src = tmp_path / "src"
    _tiny("navigation", "ppo", src, steps=32)
    ckpt = src / "checkpoints" / "agent_32.pt"
    with pytest.raises(ValueError, match="trained with --obs-mode us; .* Pass --obs-mode us"):
        _tiny("navigation", "ppo", tmp_path / "a", steps=32, init_from=ckpt,
              env_kwargs_extra={"obs_mode": "us_heading"})  # fmt: skip
    assert not (tmp_path / "a").exists()  # refused before the folder was made
    with pytest.raises(ValueError, match="--net small"):
        _tiny("navigation", "ppo", tmp_path / "b", steps=32, init_from=ckpt, net="paper")
    with pytest.raises(ValueError, match="a navigation run; this run trains surgery"):
        _tiny("surgery", "ppo", tmp_path / "c", steps=32, init_from=ckpt)
    with pytest.raises(ValueError, match="not a checkpoint of a sonogym train run"):
        stray = tmp_path / "agent_32.pt"
        stray.write_bytes(ckpt.read_bytes())
        _tiny("navigation", "ppo", tmp_path / "d", steps=32, init_from=stray)
    with pytest.raises(ValueError, match="a resumed run keeps its own"):
        _tiny("navigation", "ppo", src, steps=64, resume=True, init_from=ckpt)
    with pytest.raises(ValueError, match="unknown setting 'lr'"):
        _tiny("navigation", "ppo", tmp_path / "e", steps=32, settings={"lr": 1e-3})


@pytest.mark.parametrize(
    ("items", "message"),
    [
        (["lr=1e-3"], "unknown --set key 'lr'"),
        (["final_log_std"], "write KEY=VALUE"),
        (["anneal_steps=10", "anneal_steps=20"], "--set anneal_steps is given twice"),
        (["env.w1=0.1"], "use --seed / --env-option"),
        (["ppo.lr=1e-3"], "ppo has no setting 'lr'"),
        (["anneal_steps=-5"], "anneal_steps must be an integer >= 0"),
    ],
)
def test_cli_set_refusals(items, message, tmp_path):
    """A bad --set is refused before anything is built or written, naming the fix."""
    from typer.testing import CliRunner

    from sonogym.cli import app

    out = tmp_path / "run"
    args = ["train", "--task", "navigation", "--out", str(out)]
    for item in items:
        args += ["--set", item]
    res = CliRunner().invoke(app, args)
    text = " ".join(f"{res.output} {res.exception!r}".split())
    assert res.exit_code != 0 and message in text, text
    assert not out.exists()


def test_init_from_a_shipped_policy(tmp_path, monkeypatch):
    """A shipped policy (its folder; the CLI takes its name) is a starting point too, its cost
    taken from its model card."""
    from sonogym.agents.configs import resolve_train_config
    from sonogym.agents.train import warm_start_source
    from sonogym.cli import shipped_or_path
    from sonogym.evaluation.pretrained import export_pretrained, listing, read_card

    src = tmp_path / "src"
    _tiny("navigation", "ppo", src, steps=32)
    folder = export_pretrained(src, "tiny", root=tmp_path / "shipped")
    tuned = tmp_path / "tuned"
    _tiny("navigation", "ppo", tuned, steps=32, init_from=folder)
    start = torch.load(tuned / "checkpoints" / "agent_0.pt", weights_only=True)["policy"]
    trained = torch.load(src / "checkpoints" / "agent_32.pt", weights_only=True)["policy"]
    assert all(torch.equal(start[k], trained[k]) for k in trained)
    cfg = json.loads((tuned / "config.json").read_text())["init_from"]
    assert cfg["steps"] == 32 and cfg["checkpoint"].endswith("policy.safetensors")
    assert cfg["cpu_s"] == pytest.approx(
        60 * read_card("tiny", tmp_path / "shipped")["cpu_minutes"]
    )
    # shipped again, the fine-tuned policy's card names its source, without local paths
    again = export_pretrained(tuned, "tuned", root=tmp_path / "shipped")
    card = read_card("tuned", tmp_path / "shipped")
    assert card["init_from"] == {
        "run": "tiny",
        "checkpoint": "policy.safetensors",
        "steps_per_env": 32,
        "cpu_minutes": pytest.approx(cfg["cpu_s"] / 60, abs=0.05),
    }
    assert str(tmp_path) not in (again / "config.json").read_text()
    assert "fine-tuned from policy.safetensors of run tiny" in (again / "model_card.md").read_text()
    assert "(fine-tuned from tiny/policy.safetensors)" in listing(tmp_path / "shipped")

    monkeypatch.chdir(tmp_path)  # no file named "navigation" here: the name is the policy's
    shipped = shipped_or_path(Path("navigation"))
    assert (shipped / "policy.safetensors").is_file()
    same = resolve_train_config(
        "navigation", "ppo", preset="cpu", net="lean",
        env_kwargs={"obs_mode": read_card("navigation")["obs_mode"]},
    )  # fmt: skip
    source = warm_start_source(shipped, same)
    assert source["steps"] == read_card("navigation")["steps_per_env"]
    assert source["cpu_s"] == pytest.approx(60 * read_card("navigation")["cpu_minutes"])
    with pytest.raises(
        ValueError, match=f"trained with --obs-mode {same.rl.env_kwargs['obs_mode']}"
    ):
        warm_start_source(
            shipped, resolve_train_config("navigation", "ppo", preset="cpu", net="lean")
        )
    with pytest.raises(FileNotFoundError, match="nor a shipped policy's folder or name"):
        warm_start_source(Path("no-such-policy"), same)


def test_privileged_critic_trains_on_the_state_and_the_policy_acts_without_it(tmp_path):
    """``privileged_critic``: the critic's state branch learns (from its zero start) on the
    env's standardised ``info["state"]``; the saved policy loads and acts from observations
    alone; a run without it warm-starts one with it (the branch starts at zero), and back."""
    from sonogym.agents.train import load_train_config

    plain = tmp_path / "plain"
    _tiny("navigation", "ppo", plain, steps=32)
    run = tmp_path / "priv"
    settings = {"privileged_critic": True}
    init = plain / "checkpoints" / "agent_32.pt"
    lines = []  # the run's announcement (its cost estimate runs the critic too)
    _tiny("navigation", "ppo", run, steps=64, settings=settings, init_from=init, log=lines.append)
    assert any(line.startswith("estimated") for line in lines)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["privileged_state_size"] == 6
    assert load_train_config(run).rl.learning.privileged_critic is True
    start = torch.load(run / "checkpoints" / "agent_0.pt", weights_only=True)
    end = torch.load(run / "checkpoints" / "agent_64.pt", weights_only=True)
    source = torch.load(init, weights_only=True)["policy"]
    assert all(torch.equal(start["policy"][k], v) for k, v in source.items())
    out_w = "privileged_value.1.weight"
    assert not start["policy"][out_w].any() and end["policy"][out_w].abs().sum() > 0
    # the states were standardised with statistics of the rollouts (6 pose components)
    scaler = end["state_preprocessor"]
    assert scaler["running_mean"].shape == (6,) and float(scaler["current_count"]) > 64
    policy, _ = load_policy(run)
    obs = torch.rand(3, policy.num_observations)
    mean = policy.act({"observations": obs}, role="policy")[1]["mean_actions"]
    assert mean.shape == (3, 3) and torch.isfinite(mean).all()
    from sonogym.evaluation.pretrained import export_pretrained, weights

    folder = export_pretrained(run, "priv", root=tmp_path / "shipped")  # ships like any policy
    shipped, _ = load_policy(folder, weights("priv", tmp_path / "shipped"))
    assert torch.equal(shipped.act({"observations": obs}, role="policy")[1]["mean_actions"], mean)
    back = tmp_path / "back"  # fine-tuning without the privileged critic drops its branch
    _tiny("navigation", "ppo", back, steps=32, init_from=run / "checkpoints" / "agent_64.pt")
    assert json.loads((back / "config.json").read_text())["privileged_state_size"] == 0
    assert not any("privileged" in k for k in load_policy(back)[0].state_dict())


@pytest.mark.parametrize(
    ("task", "algo", "extra"),
    [("surgery", "ppo-lag", {}), ("navigation", "a2c", {"a2c.mini_batches": 4})],
)
def test_privileged_critic_trains_with_the_other_algorithms(task, algo, extra, tmp_path):
    """A2C and PPO-Lagrangian (its own update) feed the critic the states too."""
    _tiny(task, algo, tmp_path / "run", steps=32, settings={"privileged_critic": True, **extra})
    end = torch.load(tmp_path / "run" / "checkpoints" / "agent_32.pt", weights_only=True)
    assert end["policy"]["privileged_value.1.weight"].abs().sum() > 0
    assert torch.isfinite(end["state_preprocessor"]["running_variance"]).all()


def test_privileged_critic_refuses_single_sample_mini_batches(tmp_path):
    with pytest.raises(ValueError, match="needs >= 2 samples per mini-batch"):
        _tiny("navigation", "a2c", tmp_path / "run", steps=32, settings={"privileged_critic": True})
    assert not (tmp_path / "run").exists()  # refused before anything was built or written


def test_training_speed_figures_from_its_clock():
    """env-steps/s, the env's own speed and the learner's share follow from the loop's, the
    env's and the updates' seconds (a fake clock: no wall-clock asserts)."""
    from sonogym.agents.train import TrainingSpeed

    now = [100.0]
    speed = TrainingSpeed(64, clock=lambda: now[0])
    for _ in range(32):
        speed.add_step(env_s=0.05, update_s=0.0)
    speed.add_step(env_s=0.05, update_s=1.2)  # the step whose post_interaction updated
    now[0] += 4.0  # 33 steps: 1.65 s env, 1.2 s update, 1.15 s acting and the rest
    f = speed.figures()
    assert f["loop_s"] == pytest.approx(4.0) and f["env_s"] == pytest.approx(1.65)
    assert f["env_steps_per_s"] == pytest.approx(33 * 64 / 4.0)
    assert f["env_alone_per_s"] == pytest.approx(33 * 64 / 1.65)
    assert f["learner_share"] == pytest.approx(1 - 1.65 / 4.0)
    assert f["update_share"] == pytest.approx(0.3)
    assert speed.postfix() == {"env-steps/s": "528", "learner": "59%"}
    line = speed.summary()
    assert line.startswith("528 env-steps/s (33 steps x 64 envs in 4 s)")
    assert "1280 env-steps/s alone" in line and "0.41x the env's speed" in line
    assert "the learner 59% (updates 30%, acting, recording and checkpoints 29%)" in line


def test_speed_reporting_leaves_training_bit_identical(tmp_path):
    """A run prints its speed (the progress line and the last line) and records the loop's,
    the env's and the updates' seconds in times.json; none of it touches what training
    computes: the same seeded run with and without the display gives equal checkpoints."""
    from sonogym.agents.train import read_times

    quiet = _tiny("surgery", "ppo", tmp_path / "quiet", steps=64, checkpoint_interval=32)
    lines = []
    shown = _tiny(
        "surgery", "ppo", tmp_path / "shown", steps=64, checkpoint_interval=32,
        log=lines.append, progress=True,
    )  # fmt: skip
    for t in (0, 32, 64):
        a = torch.load(quiet.out / "checkpoints" / f"agent_{t}.pt", weights_only=True)
        b = torch.load(shown.out / "checkpoints" / f"agent_{t}.pt", weights_only=True)
        ta, tb = _tensors(a), _tensors(b)
        assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)
    assert any("env-steps/s (64 steps x 2 envs in" in line for line in lines)
    assert shown.speed["env_steps_per_s"] > 0 and 0 < shown.speed["learner_share"] < 1
    times = read_times(shown.out / "checkpoints")
    for t in (32, 64):
        e = times[t]
        assert 0 < e["env_s"] and 0 < e["update_s"] and e["env_s"] + e["update_s"] <= e["loop_s"]
    assert times[64]["loop_s"] > times[32]["loop_s"]


def test_times_written_before_the_speed_figures_still_read(tmp_path):
    from sonogym.agents.train import RunClock, read_times

    (tmp_path / "times.json").write_text(json.dumps({"32": {"cpu_s": 1.5, "wall_s": 2.0}}))
    assert read_times(tmp_path) == {32: {"cpu_s": 1.5, "wall_s": 2.0}}
    clock = RunClock(tmp_path, 32)  # a resume from it counts its loop seconds from 0
    assert clock.loop0 == {"loop_s": 0.0, "env_s": 0.0, "update_s": 0.0}


def _tensors(state, prefix=""):
    """{dotted name: tensor} of a checkpoint's nested state (optimiser state included)."""
    out = {}
    items = state.items() if isinstance(state, dict) else enumerate(state)
    for k, v in items:
        name = f"{prefix}{k}"
        if isinstance(v, torch.Tensor):
            out[name] = v
        elif isinstance(v, (dict, list, tuple)):
            out.update(_tensors(v, name + "."))
    return out
