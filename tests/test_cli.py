"""The command line's refusals: an existing subject or run folder is never mixed into, and
--force deletes only what sonogym wrote there, saying what."""

from __future__ import annotations

from typer.testing import CliRunner

from sonogym.cli import app


def _tree(path):
    return {
        str(p.relative_to(path)): (p.read_bytes() if p.is_file() else None)
        for p in sorted(path.rglob("*"))
    }


def test_phantom_never_replaces_a_subject_folder_it_did_not_write(tmp_path):
    out = tmp_path / "subject"
    out.mkdir()
    (out / "ct.nii.gz").write_bytes(b"a patient's CT")  # a real subject: ct.nii.gz, no marker
    runner = CliRunner()
    args = ["phantom", "--seed", "0", "--spacing", "2", "--out", str(out), "--no-preview"]
    res = runner.invoke(app, args)
    assert res.exit_code != 0 and "--force" in str(res.exception or res.output)
    res = runner.invoke(app, [*args, "--force"])
    assert res.exit_code != 0
    assert "Delete it by hand" in str(res.exception) and "another output folder" in str(
        res.exception
    )
    assert _tree(out) == {"ct.nii.gz": b"a patient's CT"}  # nothing deleted, nothing written


def test_phantom_force_replaces_its_own_subject_folder_and_says_what_it_deleted(tmp_path):
    from sonogym.runs import read_marker

    out = tmp_path / "subject"
    runner = CliRunner()
    args = ["phantom", "--seed", "0", "--spacing", "2", "--out", str(out), "--no-preview"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert read_marker(out)["kind"] == "subject"
    assert (out / "ct.nii.gz").stat().st_size > 1000 and (out / "segmentations").is_dir()
    res = runner.invoke(app, [*args, "--force"])
    assert res.exit_code == 0, res.output
    assert "--force: deleted ct.nii.gz, segmentations/, sonogym.json from" in res.output
    assert (out / "ct.nii.gz").stat().st_size > 1000


def test_train_force_never_deletes_a_folder_holding_a_config_json_of_the_users(tmp_path):
    project = tmp_path / "project"
    (project / "src").mkdir(parents=True)
    (project / "src" / "model.py").write_text("print('years of work')\n")
    (project / "thesis.pdf").write_bytes(b"%PDF-1.7")
    (project / "config.json").write_text('{"lr": 0.001}')
    before = _tree(project)
    args = ["train", "--task", "navigation", "--out", str(project), "--force", "--steps", "4",
            "--envs", "1", "--phantom-spacing", "2"]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code != 0
    assert "no .sonogym marker" in str(res.exception)
    assert _tree(project) == before


def test_a_symlink_loop_given_as_a_patient_is_named_not_a_traceback(tmp_path):
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    out = tmp_path / "demo"
    res = CliRunner().invoke(app, ["demo", "--patient", str(tmp_path / "a"), "--out", str(out)])
    # a ValueError is what main() prints as one "sonogym: error:" line
    assert isinstance(res.exception, ValueError), res.exception
    msg = str(res.exception)
    assert f"patient folder {tmp_path / 'a'}" in msg and "symlink" in msg
