"""The command line's refusals: an existing subject folder is never mixed into."""

from __future__ import annotations

from typer.testing import CliRunner

from sonogym.cli import app


def test_phantom_refuses_an_existing_subject_folder_unless_forced(tmp_path):
    out = tmp_path / "subject"
    out.mkdir()
    (out / "ct.nii.gz").write_bytes(b"someone else's CT")
    runner = CliRunner()
    args = ["phantom", "--seed", "0", "--spacing", "2", "--out", str(out), "--no-preview"]
    res = runner.invoke(app, args)
    assert res.exit_code != 0 and "--force" in str(res.exception or res.output)
    assert (out / "ct.nii.gz").read_bytes() == b"someone else's CT"  # nothing written
    res = runner.invoke(app, [*args, "--force"])
    assert res.exit_code == 0, res.output
    assert (out / "ct.nii.gz").stat().st_size > 1000 and (out / "segmentations").is_dir()


def test_a_symlink_loop_given_as_a_patient_is_named_not_a_traceback(tmp_path):
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    out = tmp_path / "demo"
    res = CliRunner().invoke(app, ["demo", "--patient", str(tmp_path / "a"), "--out", str(out)])
    # a ValueError is what main() prints as one "sonogym: error:" line
    assert isinstance(res.exception, ValueError), res.exception
    msg = str(res.exception)
    assert f"patient folder {tmp_path / 'a'}" in msg and "symlink" in msg
