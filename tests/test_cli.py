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
