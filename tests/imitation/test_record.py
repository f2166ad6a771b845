"""Expert datasets from the envs: what is written is what the expert saw and did, an
interrupted recording resumes without duplicates, failed expert episodes are counted, and an IL
policy trained on one runs through ``sonogym eval``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sonogym.cli import app
from sonogym.envs.identity import identity
from sonogym.envs.policy import ExpertPolicy
from sonogym.envs.registry import get_task, make_vec
from sonogym.envs.rollout import rollout
from sonogym.imitation import record as rec
from sonogym.imitation.lerobot_format import read_info
from sonogym.imitation.reader import LeRobotFrames

NAV = dict(phantom_spacing=0.002, episode_length=40)


def _record(out, episodes=3, envs=2, **kw):
    torch.set_num_threads(1)
    return rec.record("navigation", out, episodes=episodes, envs=envs, env_kwargs=NAV,
                      progress=False, log=lambda m: None, **kw)  # fmt: skip


def test_round_trip_equals_the_rolled_out_frames_and_actions(tmp_path):
    res = _record(tmp_path / "d", episodes=2, envs=2)
    assert (res.episodes, res.frames, res.failed) == (2, 80, 0)
    # the same batch again, by hand
    env = make_vec("navigation", 2, **NAV)
    images, actions = [], []
    for step in rollout(env, ExpertPolicy(env, get_task("navigation").expert), 40, seed=0):
        images.append(rec.quantize_images(step.obs))
        actions.append(step.action)
    images, actions = torch.stack(images, 1), torch.stack(actions, 1)  # (N, T, ...)
    ds = LeRobotFrames(tmp_path / "d")
    for i in range(80):
        f = ds[i]
        ep, t = int(f["episode_index"]), int(f["frame_index"])
        want = images[ep, t].float() / 255
        assert torch.equal(f["observation.images.us"], want)  # 8-bit quantised, exactly
        assert torch.allclose(f["action"], actions[ep, t])
    info = read_info(tmp_path / "d")
    assert info["codebase_version"] == "v3.0" and info["fps"] == 60
    assert info["features"]["observation.images.us"]["shape"] == [200, 150, 1]
    assert info["features"]["action"]["names"] == ["dx", "dy", "dalpha"]
    stats = json.loads((tmp_path / "d" / "meta" / "stats.json").read_text())
    a = actions.reshape(-1, 3).numpy()
    np.testing.assert_allclose(stats["action"]["mean"], a.mean(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(stats["action"]["max"], a.max(0), rtol=1e-6)


def test_interrupted_recording_resumes_without_duplicates(tmp_path, monkeypatch):
    full = _record(tmp_path / "full", episodes=5, envs=2)
    from sonogym.imitation.writer import DatasetWriter

    real = DatasetWriter.add_episode
    calls = {"n": 0}

    def dying(self, frames, task=None):
        calls["n"] += 1
        if calls["n"] == 4:  # killed during the second batch's second episode
            raise KeyboardInterrupt
        return real(self, frames, task)

    monkeypatch.setattr(DatasetWriter, "add_episode", dying)
    with pytest.raises(KeyboardInterrupt):
        _record(tmp_path / "cut", episodes=5, envs=2)
    monkeypatch.setattr(DatasetWriter, "add_episode", real)
    assert read_info(tmp_path / "cut")["total_episodes"] == 3
    with pytest.raises(FileExistsError, match="--resume"):
        _record(tmp_path / "cut", episodes=5, envs=2)
    res = rec.record("navigation", tmp_path / "cut", resume=True, progress=False,
                     log=lambda m: None)  # fmt: skip
    assert res.episodes == full.episodes == 5
    a, b = LeRobotFrames(tmp_path / "full"), LeRobotFrames(tmp_path / "cut")
    assert len(a) == len(b) == 200
    for i in range(0, 200, 7):  # the same episodes in the same order: no duplicate, no gap
        fa, fb = a[i], b[i]
        assert int(fa["index"]) == int(fb["index"]) == i
        assert torch.equal(fa["observation.images.us"], fb["observation.images.us"])
        assert torch.equal(fa["action"], fb["action"])
    with pytest.raises(ValueError, match="envs"):
        rec.record("navigation", tmp_path / "cut", resume=True, envs=3, progress=False)


@pytest.mark.parametrize("death", [KeyboardInterrupt(), OSError(28, "No space left on device")])
def test_a_recording_interrupted_in_its_first_batch_resumes(tmp_path, monkeypatch, death):
    from sonogym.imitation.writer import DatasetWriter

    real = DatasetWriter.add_episode
    calls = {"n": 0}

    def dying(self, frames, task=None):
        calls["n"] += 1
        if calls["n"] == 2:  # Ctrl-C or a full disk in the first batch's second episode
            raise death
        return real(self, frames, task)

    monkeypatch.setattr(DatasetWriter, "add_episode", dying)
    with pytest.raises(type(death)):
        _record(tmp_path / "cut", episodes=3, envs=2)
    monkeypatch.setattr(DatasetWriter, "add_episode", real)
    assert read_info(tmp_path / "cut")["total_episodes"] == 1
    with pytest.raises(FileExistsError, match="--resume.*--force"):
        _record(tmp_path / "cut", episodes=3, envs=2)
    res = rec.record("navigation", tmp_path / "cut", resume=True, progress=False,
                     log=lambda m: None)  # fmt: skip
    assert res.episodes == 3
    full = _record(tmp_path / "full", episodes=3, envs=2)
    a, b = LeRobotFrames(tmp_path / "full"), LeRobotFrames(tmp_path / "cut")
    assert full.frames == len(a) == len(b) == 120
    for i in range(0, 120, 9):
        assert torch.equal(a[i]["observation.images.us"], b[i]["observation.images.us"])
        assert torch.equal(a[i]["action"], b[i]["action"])


def test_a_recording_killed_before_its_first_episode_can_be_forced(tmp_path, monkeypatch):
    from sonogym.imitation.writer import DatasetWriter

    def killed(self, frames, task=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(DatasetWriter, "add_episode", killed)
    with pytest.raises(KeyboardInterrupt):
        _record(tmp_path / "cut", episodes=2, envs=1)
    monkeypatch.undo()
    logged = []
    res = rec.record("navigation", tmp_path / "cut", episodes=2, envs=1, env_kwargs=NAV,
                     force=True, progress=False, log=logged.append)  # fmt: skip
    assert res.episodes == 2 and "--force: deleted meta/ from" in logged[0]


def test_a_second_recording_into_a_folder_in_use_is_refused(tmp_path, folder_in_use):
    first = folder_in_use(tmp_path / "d", "dataset")
    with pytest.raises(FileExistsError, match=rf"d is in use .*pid {first.pid}"):
        _record(tmp_path / "d", episodes=1, envs=1)
    assert not (tmp_path / "d" / "meta").exists()


def test_failed_expert_episodes_are_counted_not_written(tmp_path):
    # 3 steps are too few for the expert to reach the goal: every episode fails
    with pytest.raises(RuntimeError, match="failed every episode"):
        rec.record("navigation", tmp_path / "d", episodes=2, envs=1, progress=False,
                   env_kwargs=dict(phantom_spacing=0.002, episode_length=3),
                   log=lambda m: None)  # fmt: skip
    meta = rec.read_recording(tmp_path / "d")
    assert meta["failed"] == 10 and meta["episodes_written"] == 0
    assert read_info(tmp_path / "d")["total_episodes"] == 0


@pytest.mark.parametrize("task,mode", [("navigation", "us_heading"), ("surgery", "state")])
def test_a_mode_other_than_the_datasets_is_refused_before_anything_is_written(tmp_path, task, mode):
    with pytest.raises(ValueError, match="datasets record the default observation"):
        rec.record(task, tmp_path / "d", episodes=1, envs=1, progress=False,
                   env_kwargs={"obs_mode": mode}, log=lambda m: None)  # fmt: skip
    assert not (tmp_path / "d").exists()


def test_a_force_action_is_refused_before_anything_is_written(tmp_path):
    """The datasets' actions are the task's: a force action would add one they do not name."""
    with pytest.raises(ValueError, match="force_action adds one they do not name"):
        rec.record("navigation", tmp_path / "d", episodes=1, envs=1, progress=False,
                   env_kwargs={"force_action": True}, log=lambda m: None)  # fmt: skip
    assert not (tmp_path / "d").exists()


def test_recipes_are_the_papers_settings():
    nav = rec.dataset_spec("navigation")
    assert [(p.name, p.episodes) for p in nav.recipes] == [
        ("mb", 2052), ("lb", 1869), ("lb-4-nets", 954)
    ]  # fmt: skip
    sur = rec.dataset_spec("surgery")
    assert [(p.name, p.episodes) for p in sur.recipes] == [
        ("mb", 3536), ("mb-5-patients", 1476), ("lb", 2052), ("lb-4-nets", 2692)
    ]  # fmt: skip
    assert sur.recipe("mb-5-patients").env_kwargs["patients"] == (0, 1, 2, 3, 4)
    assert sur.recipe("lb-4-nets").env_kwargs["learned_nets"] == (0, 1, 2, 3)
    # the appendix's wider data-collection starts, which may be unsafe
    assert sur.recipe("mb").env_kwargs["joint_noise"] == (0.3, 0.25, 0.2, 0.2, 0.2, 0.2, 0.1)
    assert sur.recipe("mb").env_kwargs["require_free_start"] is False
    with pytest.raises(ValueError, match="unknown dataset recipe"):
        sur.recipe("xl")


def test_cli_record_il_train_and_eval_an_il_run(tmp_path):
    runner = CliRunner()
    data, run = tmp_path / "data", tmp_path / "act"
    args = ["--episodes", "2", "--envs", "2", "--phantom-spacing", "2"]
    res = runner.invoke(app, ["record", "--task", "navigation", "--out", str(data), *args])
    assert res.exit_code == 0, res.output
    assert "MiB per episode" in res.output and "wrote 2 episodes" in res.output
    bad = runner.invoke(app, ["il-train", "--policy", "act", "--data", str(data), "--out",
                              str(run), "--image-size", "100"])  # fmt: skip
    assert bad.exit_code != 0 and "HxW" in bad.output and not run.exists()
    res = runner.invoke(app, ["il-train", "--policy", "act", "--data", str(data), "--out",
                              str(run), "--steps", "3", "--image-size", "50x37"])  # fmt: skip
    assert res.exit_code == 0, res.output
    cfg = json.loads((run / "config.json").read_text())
    assert (cfg["task"], cfg["algo"]) == ("navigation", "act")
    assert cfg["policy_config"]["image_size"] == [50, 37]  # the cpu size, images resampled
    assert cfg["policy_config"]["chunk_size"] == 20
    assert cfg["env_kwargs"] == {"phantom_spacing": 0.002}
    # the dataset and the run trained on it record the identity it was recorded under
    made = identity("navigation", {"phantom_spacing": 0.002})
    assert cfg["identity"] == made
    assert json.loads((data / "meta" / "info.json").read_text())["sonogym_identity"] == made
    res = runner.invoke(app, ["eval", "--run", str(run), "--trials", "2", "--envs", "2"])
    assert res.exit_code == 0, res.output
    assert "| policy |" in res.output and (run / "episodes" / "idt.npz").is_file()
