"""One run-folder reader for RL and IL runs (``sonogym.runs.RunFolder``): checkpoints listed
oldest first by their step (not by file name), the newest readable one found past torn ones,
and the kind told by config.json."""

from __future__ import annotations

import json

import pytest
import torch

from sonogym.agents.checkpoint import RL_RUN
from sonogym.imitation.run import IL_RUN, RUN_KIND, save_checkpoint
from sonogym.runs import RunFolder, open_run


def _rl_checkpoint(path, value):
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"policy": {"w": torch.full((2,), float(value))}}, path)


def test_rl_checkpoints_oldest_first_by_step_and_the_newest_readable_past_torn_ones(tmp_path):
    ck = tmp_path / "checkpoints"
    for t in (0, 9, 64, 640):
        _rl_checkpoint(ck / f"agent_{t}.pt", t)
    (ck / "agent_1000.pt").write_bytes(b"")  # a save killed half-way
    (ck / "agent_2000.pt.tmp4242").write_bytes(b"x")  # a save in flight: not a checkpoint
    (ck / "times.json").write_text("{}")
    run = RunFolder(tmp_path, RL_RUN)
    # by step: the file names sort as 0, 1000, 64, 640, 9
    assert [s for s, _ in run.checkpoints()] == [0, 9, 64, 640, 1000]
    warned = []
    found = run.newest_readable_checkpoint(warn=warned.append)
    assert (found.step, found.path.name) == (640, "agent_640.pt")
    assert torch.equal(found.state["policy"]["w"], torch.full((2,), 640.0))
    assert len(warned) == 1 and "agent_1000.pt" in warned[0]
    with pytest.warns(UserWarning, match="agent_1000.pt"):
        assert run.require_checkpoint().step == 640
    assert RL_RUN.step_of(tmp_path / "copy_of_agent_64.pt") == 64


def test_il_checkpoints_the_same_way_and_none_readable_is_named(tmp_path):
    for step in (5, 20, 100):
        save_checkpoint(tmp_path, step, {"model": {}, "step": step})
    (tmp_path / "checkpoints" / "step_000000200.pt").write_bytes(b"\x00" * 10)  # corrupt
    run = RunFolder(tmp_path, IL_RUN)
    assert [s for s, _ in run.checkpoints()] == [5, 20, 100, 200]
    with pytest.warns(UserWarning, match="step_000000200.pt"):
        assert run.newest_readable_checkpoint().state["step"] == 100
    empty = RunFolder(tmp_path / "new", IL_RUN)
    assert empty.checkpoints() == [] and empty.newest_readable_checkpoint() is None
    with pytest.raises(FileNotFoundError, match=r"no readable checkpoints/step_\*\.pt in .*new"):
        empty.require_checkpoint()


def test_config_json_tells_the_kind(tmp_path):
    (tmp_path / "il").mkdir()
    (tmp_path / "rl").mkdir()
    (tmp_path / "il" / "config.json").write_text(json.dumps({"kind": RUN_KIND, "task": None}))
    (tmp_path / "rl" / "config.json").write_text(json.dumps({"task": "navigation"}))
    assert open_run(tmp_path / "il", (RL_RUN, IL_RUN)).kind is IL_RUN
    assert open_run(tmp_path / "rl", (RL_RUN, IL_RUN)).kind is RL_RUN
    with pytest.raises(FileNotFoundError, match="`sonogym train` / `sonogym il-train` run"):
        open_run(tmp_path, (RL_RUN, IL_RUN))
