"""IL runs that cannot be lost: a torn newest checkpoint is skipped by name, a resume refuses
changed options by name, Ctrl-C saves and says how to resume, a broken config.json is named."""

from __future__ import annotations

import json
import re

import pytest
import torch

from sonogym.imitation.policies.act import ACTConfig
from sonogym.imitation.run import IL_RUN, load_checkpoint, load_model, read_run_config
from sonogym.imitation.train import ILTrainConfig, train_il
from sonogym.runs import (
    CheckpointError,
    RunFolder,
    TrainingInterrupted,
    atomic_write_json,
    read_json,
)

TINY_ACT = ACTConfig.cpu(
    chunk_size=4, n_action_steps=4, backbone_widths=(8, 16), backbone_blocks=(1, 1),
    dim_model=32, n_heads=2, dim_feedforward=64, n_encoder_layers=1, n_vae_encoder_layers=1,
    latent_dim=4, dropout=0.0,
)  # fmt: skip


def checkpoints(run):
    return RunFolder(run, IL_RUN).checkpoints()


def _cfg(data, out, **kw):
    base = dict(data=str(data), out=str(out), policy="act", policy_config=TINY_ACT, steps=20,
                batch_size=4, save_every=10, log_every=10, progress=False)  # fmt: skip
    return ILTrainConfig(**{**base, **kw})


def test_torn_newest_checkpoint_is_skipped_by_name(blob_dataset, tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    train_il(_cfg(blob_dataset, run))
    torn = run / "checkpoints" / "step_000000030.pt"
    torn.write_bytes(b"")  # a save killed half-way by an older version
    with pytest.raises(CheckpointError, match="step_000000030.pt is not a readable"):
        load_checkpoint(torn)
    warned = []
    found = RunFolder(run, IL_RUN).newest_readable_checkpoint(warn=warned.append)
    path, state = found.path, found.state
    assert path.name == "step_000000020.pt" and state["step"] == 20
    assert len(warned) == 1 and "step_000000030.pt" in warned[0]
    with pytest.warns(UserWarning, match="step_000000030.pt"):
        load_model(run)  # evaluation's default checkpoint
    # resume continues from the readable one
    res = train_il(_cfg(blob_dataset, run, steps=30, resume=True))
    assert res.steps == 30 and load_checkpoint(torn)["step"] == 30


def test_resume_refuses_changed_options_by_name(blob_dataset, tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    train_il(_cfg(blob_dataset, run))
    before = (run / "config.json").read_bytes()
    for kw, name in (
        (dict(seed=7), "seed 7 (run: 1000)"),
        (dict(batch_size=8), "batch_size 8 (run: 4)"),
        (
            dict(
                policy_config=ACTConfig(
                    **{**TINY_ACT.__dict__, "chunk_size": 5, "n_action_steps": 5}
                )
            ),
            "policy_config.chunk_size 5",
        ),  # fmt: skip
    ):
        with pytest.raises(ValueError, match=name.replace("(", r"\(").replace(")", r"\)")):
            train_il(_cfg(blob_dataset, run, steps=30, resume=True, **kw))
        assert (run / "config.json").read_bytes() == before  # refused before touching it
    with pytest.raises(ValueError, match="trained 20 steps already"):
        train_il(_cfg(blob_dataset, run, steps=10, resume=True))


def test_ctrl_c_saves_and_says_how_to_resume(blob_dataset, tmp_path, monkeypatch, capsys):
    torch.set_num_threads(1)
    from sonogym.imitation.policies.act import modeling as act

    calls = {"n": 0}
    real = act.ACTPolicy.compute_loss

    def interrupted(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 14:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(act.ACTPolicy, "compute_loss", interrupted)
    run = tmp_path / "run"
    with pytest.raises(TrainingInterrupted, match="--resume"):
        train_il(_cfg(blob_dataset, run, steps=40))
    assert "interrupted after 13 of 40 steps" in capsys.readouterr().out
    assert [s for s, _ in checkpoints(run)] == [10, 13]  # nothing since step 10 was lost
    monkeypatch.setattr(act.ACTPolicy, "compute_loss", real)
    assert train_il(_cfg(blob_dataset, run, steps=40, resume=True)).steps == 40


def test_broken_run_config_is_named(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"config.json is not valid JSON"):
        read_run_config(run)
    (run / "config.json").write_text(json.dumps({"kind": "sonogym-il-run"}))
    with pytest.raises(ValueError, match=r"lacks \['policy'"):
        read_run_config(run)


def test_json_writes_survive_paths_that_are_not_utf8(tmp_path):
    odd = str(tmp_path) + "/subj-\udcff\udcfe"  # how Python names a non-UTF-8 folder
    atomic_write_json(tmp_path / "c.json", {"patients": [odd]})
    assert read_json(tmp_path / "c.json", "test")["patients"] == [odd]


def test_force_never_deletes_a_folder_holding_a_config_json_of_the_users(blob_dataset, tmp_path):
    project = tmp_path / "project"
    (project / "src").mkdir(parents=True)
    (project / "src" / "model.py").write_text("print('years of work')\n")
    (project / "config.json").write_text('{"lr": 0.001}')
    with pytest.raises(FileExistsError, match="no .sonogym marker.*Delete it by hand"):
        train_il(_cfg(blob_dataset, project, force=True))
    assert sorted(p.name for p in project.rglob("*")) == ["config.json", "model.py", "src"]


def test_a_second_run_into_a_folder_in_use_is_refused(blob_dataset, tmp_path, folder_in_use):
    run = tmp_path / "run"
    first = folder_in_use(run, "il-run")  # e.g. an ACT run training into it
    with pytest.raises(FileExistsError, match=rf"{run} is in use .*pid {first.pid}"):
        train_il(_cfg(blob_dataset, run, policy="diffusion", policy_config=None))
    assert not (run / "config.json").exists()


def test_checkpoint_every_is_an_option(blob_dataset, tmp_path):
    from typer.testing import CliRunner

    from sonogym.cli import app

    torch.set_num_threads(1)
    run = tmp_path / "run"
    args = ["il-train", "--policy", "act", "--data", str(blob_dataset), "--out", str(run),
            "--steps", "5", "--batch-size", "2", "--checkpoint-every", "2"]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    assert [s for s, _ in checkpoints(run)] == [2, 4, 5]
    assert read_run_config(run)["train"]["save_every"] == 2


def test_time_based_checkpoints_replace_each_other(blob_dataset, tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    # a checkpoint every 60 us of training: after every step (each takes longer)
    train_il(_cfg(blob_dataset, run, steps=6, save_every=1000, save_minutes=1e-6))
    # each time-based one replaced the one before; the final one is always written
    assert [s for s, _ in checkpoints(run)] == [5, 6]
    with pytest.raises(ValueError, match="save_minutes must be >= 0"):
        _cfg(blob_dataset, run, save_minutes=-1)


def test_an_undecodable_frame_is_named_and_training_saves_before_it_stops(
    blob_dataset, tmp_path, capsys
):
    import re
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    from sonogym.imitation import lerobot_format as fmt
    from sonogym.imitation.reader import read_episodes

    torch.set_num_threads(1)
    data = tmp_path / "data"
    shutil.copytree(blob_dataset, data)
    ep = read_episodes(data)[3]
    path = fmt.data_file(data, ep["data/chunk_index"], ep["data/file_index"])
    t = pq.read_table(path)
    key = "observation.images.cam"
    col = t.column(key).combine_chunks()
    rows = [e == 3 for e in t.column("episode_index").to_pylist()]
    damaged = [b"\x89PNG\r\n\x1a\n broken" if bad else b for b, bad in
               zip(col.field("bytes").to_pylist(), rows, strict=True)]  # fmt: skip
    images = pa.StructArray.from_arrays(
        [pa.array(damaged, pa.binary()), col.field("path")], names=["bytes", "path"]
    )
    pq.write_table(t.set_column(t.schema.get_field_index(key), t.schema.field(key), images), path)
    run = tmp_path / "run"
    pattern = rf"{re.escape(str(path))} \(row \d+\): episode 3, frame \d+ .*key '{key}'"
    with pytest.raises(fmt.DatasetFormatError, match=pattern):
        train_il(_cfg(data, run, steps=200, save_every=1000, save_minutes=0))
    out = capsys.readouterr().out
    step = int(re.search(r"stopped at step (\d+) of 200", out).group(1))
    assert [s for s, _ in checkpoints(run)] == [step] and "--resume" in out


def test_a_corrupt_dataset_is_refused_before_the_run_folder_is_touched(blob_dataset, tmp_path):
    import shutil

    from il_datasets import set_value

    torch.set_num_threads(1)
    run = tmp_path / "run"
    train_il(_cfg(blob_dataset, run, steps=10))
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    data = tmp_path / "nan"
    shutil.copytree(blob_dataset, data)
    set_value(data, "action", 30, 1, float("nan"))  # one NaN trained all-NaN weights, exit 0
    with pytest.raises(ValueError, match=r"episode 1, frame 6, column action\[1\] is nan"):
        train_il(_cfg(data, run, steps=10, force=True))
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before  # not replaced
    with pytest.raises(ValueError, match="frame 6"):
        train_il(_cfg(data, tmp_path / "new", steps=10))
    assert not (tmp_path / "new").exists()


def _as_navigation_dataset(blob_dataset, tmp_path):
    """The blob dataset with a recording note that says navigation (its features are not)."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(blob_dataset, data)
    atomic_write_json(data / "meta" / "sonogym.json", {"task": "navigation", "env_kwargs": {}})
    return data


def test_a_dataset_of_another_task_is_refused_at_il_train(blob_dataset, tmp_path):
    data = _as_navigation_dataset(blob_dataset, tmp_path)
    with pytest.raises(ValueError, match=r"names task 'navigation', but the features .* are not"):
        train_il(_cfg(data, tmp_path / "run", steps=10))
    assert not (tmp_path / "run").exists()


def test_eval_refuses_an_il_run_of_another_task_before_building_an_env(
    blob_dataset, tmp_path, monkeypatch
):
    from typer.testing import CliRunner

    from sonogym.cli import app
    from sonogym.envs import registry
    from sonogym.evaluation.trained import load_run

    torch.set_num_threads(1)
    run = tmp_path / "run"
    train_il(_cfg(blob_dataset, run, steps=10))
    cfg = json.loads((run / "config.json").read_text())
    atomic_write_json(run / "config.json", {**cfg, "task": "navigation"})  # a run trained
    # before il-train checked the task, or an edited config: it failed in the first step
    with pytest.raises(ValueError, match="config.json names task 'navigation'"):
        load_run(run)

    def no_env(*a, **k):
        raise AssertionError("an env was built")

    monkeypatch.setattr(registry, "make_vec", no_env)
    res = CliRunner().invoke(app, ["eval", "--run", str(run), "--trials", "1"])
    assert res.exit_code != 0 and "names task 'navigation'" in res.output
    for change, message in (
        ({"algo": "ppo"}, "algo 'ppo' (act or dp)"),
        ({"seed": "x"}, "seed 'x' (an integer)"),
        ({"env_kwargs": {"w1": "high"}}, "NavigationConfig.w1 must be a finite number"),
        ({"task": "bogus"}, "task 'bogus' is not a sonogym task"),
    ):
        atomic_write_json(run / "config.json", {**cfg, "task": "navigation", **change})
        with pytest.raises(ValueError, match=re.escape(message)):
            load_run(run)
