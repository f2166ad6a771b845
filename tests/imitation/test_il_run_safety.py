"""IL runs that cannot be lost: a torn newest checkpoint is skipped by name, a resume refuses
changed options by name, Ctrl-C saves and says how to resume, a broken config.json is named."""

from __future__ import annotations

import json

import pytest
import torch

from sonogym.imitation.act import ACTConfig
from sonogym.imitation.run import (
    checkpoints,
    load_checkpoint,
    load_model,
    newest_readable_checkpoint,
    read_run_config,
)
from sonogym.imitation.train import ILTrainConfig, train_il
from sonogym.runs import CheckpointError, TrainingInterrupted, atomic_write_json, read_json

TINY_ACT = ACTConfig.cpu(
    chunk_size=4, n_action_steps=4, backbone_widths=(8, 16), backbone_blocks=(1, 1),
    dim_model=32, n_heads=2, dim_feedforward=64, n_encoder_layers=1, n_vae_encoder_layers=1,
    latent_dim=4, dropout=0.0,
)  # fmt: skip


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
    path, state = newest_readable_checkpoint(run, warn=warned.append)
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
    from sonogym.imitation import act

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
