"""The output-folder rule: --force deletes only what sonogym wrote (its marker, its entries) and
says what; a folder in use by another process is refused, naming the process; the lock dies
with its process, SIGKILL included."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

from sonogym.runs import (
    LOCK,
    MARKER,
    OutputExistsError,
    OutputInUseError,
    OutputLock,
    clear_output,
    prepare_output,
    read_marker,
)


def _tree(path: Path) -> dict[str, bytes | None]:
    return {
        str(p.relative_to(path)): (p.read_bytes() if p.is_file() else None)
        for p in sorted(path.rglob("*"))
    }


def _project_folder(path: Path) -> Path:
    """A user's folder that happens to hold a config.json: a project with code and a thesis."""
    (path / "src").mkdir(parents=True)
    (path / "src" / "model.py").write_text("print('years of work')\n")
    (path / "thesis.pdf").write_bytes(b"%PDF-1.7 chapter 1")
    (path / "config.json").write_text('{"lr": 0.001}')
    return path


def test_a_new_folder_is_marked_with_its_kind_and_command(tmp_path):
    with prepare_output(tmp_path / "run", resume=False, force=False, kind="rl-run") as out:
        assert not out.resumed and out.deleted == ()
    marker = read_marker(tmp_path / "run")
    assert (marker["kind"], marker["command"]) == ("rl-run", "sonogym train")
    # an empty existing folder is used as it is, and marked
    (tmp_path / "empty").mkdir()
    prepare_output(tmp_path / "empty", False, False, "dataset").release()
    assert read_marker(tmp_path / "empty")["kind"] == "dataset"


def test_force_never_deletes_a_folder_sonogym_did_not_mark(tmp_path):
    project = _project_folder(tmp_path / "project")
    before = _tree(project)
    for kind in ("rl-run", "il-run"):
        with pytest.raises(OutputExistsError, match="no .sonogym marker.*Delete it by hand"):
            prepare_output(project, resume=False, force=True, kind=kind)
    assert _tree(project) == before  # nothing deleted, nothing (not even a lock) written


def test_force_refuses_a_marked_folder_holding_the_users_files_and_names_them(tmp_path):
    run = tmp_path / "run"
    prepare_output(run, False, False, "rl-run").release()
    (run / "config.json").write_text("{}")
    (run / "checkpoints").mkdir()
    (run / "src").mkdir()
    (run / "thesis.pdf").write_bytes(b"%PDF")
    before = _tree(run)
    with pytest.raises(OutputExistsError, match=r"holds src/, thesis.pdf, which sonogym train"):
        prepare_output(run, resume=False, force=True, kind="rl-run")
    assert _tree(run) == before


def test_force_refuses_a_folder_of_another_kind(tmp_path):
    data = tmp_path / "data"
    prepare_output(data, False, False, "dataset").release()
    (data / "meta").mkdir()
    before = _tree(data)
    with pytest.raises(OutputExistsError, match="holds a dataset .written by sonogym record.*not"):
        prepare_output(data, resume=False, force=True, kind="rl-run")
    with pytest.raises(OutputExistsError, match="holds a dataset"):
        prepare_output(data, resume=True, force=False, kind="il-run")
    assert _tree(data) == before


def test_force_deletes_only_what_the_kind_writes_and_lists_it(tmp_path):
    run = tmp_path / "run"
    prepare_output(run, False, False, "rl-run").release()
    (run / "config.json").write_text("{}")
    (run / "checkpoints").mkdir()
    (run / "checkpoints" / "agent_0.pt").write_bytes(b"w")
    (run / "events.out.tfevents.1.host.2.0").write_bytes(b"tb")
    (run / "eval.json").write_text("{}")
    (run / "config.json.tmp99999999").write_text("{")  # a killed write's leftover
    with prepare_output(run, resume=False, force=True, kind="rl-run") as out:
        assert sorted(out.deleted) == [
            "checkpoints/", "config.json", "config.json.tmp99999999",
            "eval.json", "events.out.tfevents.1.host.2.0",
        ]  # fmt: skip
    assert sorted(p.name for p in run.iterdir()) == sorted([MARKER, LOCK])
    assert clear_output(run, "rl-run") == []  # an empty marked folder: nothing to delete


def test_a_refused_new_folder_is_left_as_it_was(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing to resume"):
        prepare_output(tmp_path / "new", resume=True, force=False, kind="il-run")
    assert not (tmp_path / "new").exists()
    with pytest.raises(RuntimeError):
        with prepare_output(tmp_path / "new", resume=False, force=False, kind="il-run"):
            raise RuntimeError("bad input found after the folder was prepared")
    assert not (tmp_path / "new").exists()


def test_two_locks_on_one_folder_exclude_each_other(tmp_path):
    first = OutputLock(tmp_path / "run").acquire()
    with pytest.raises(OutputInUseError, match=rf"run is in use .*pid {os.getpid()}\)"):
        OutputLock(tmp_path / "run").acquire()
    first.release()
    OutputLock(tmp_path / "run").acquire().release()


def test_a_folder_in_use_is_refused_naming_the_process_even_with_force(tmp_path, folder_in_use):
    run = tmp_path / "run"
    proc = folder_in_use(run, "rl-run")
    (run / "config.json").write_text("{}")  # the first run has started writing
    for resume, force in ((False, False), (False, True), (True, False)):
        with pytest.raises(OutputInUseError, match=rf"{run} is in use .*pid {proc.pid}"):
            prepare_output(run, resume=resume, force=force, kind="rl-run")
    assert (run / "config.json").read_text() == "{}"
    # SIGKILL: the OS drops the lock with the process; the run can be resumed at once
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    with prepare_output(run, resume=True, force=False, kind="rl-run") as out:
        assert out.resumed
    assert json.loads((run / "config.json").read_text()) == {}
