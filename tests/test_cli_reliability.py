"""The newer commands (export, view, eval --pretrained, reproduce, morphometry) as a hostile but
ordinary user drives them: a user's files are never replaced or deleted without --force, a failed
command leaves nothing it made, errors are one line, long steps say what they do, and the
commands work outside a checkout. Each test is one probe's input."""

from __future__ import annotations

import json
import os
import shutil
import sys
import warnings
from pathlib import Path

import pytest

from sonogym.cli import main

SUBJECT = Path(__file__).resolve().parent / "data" / "totalsegmentator_example"


def sonogym(monkeypatch, capsys, *args) -> tuple[int, str, str]:
    """Run the ``sonogym`` entry point as a user's shell would: (exit status, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["sonogym", *map(str, args)])
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(code: int, err: str) -> str:
    """The error line of a failed command (checked: non-zero exit, the error in one line on
    stderr, after any progress lines, and no traceback)."""
    assert code != 0
    lines = [line for line in err.splitlines() if line.strip()]
    said = [line for line in lines if line.startswith("sonogym: ")]
    assert len(said) == 1 and lines[-1] == said[0], err
    assert "Traceback" not in err
    return said[0]


def tree(path: Path) -> dict[str, bytes | None]:
    return {
        str(p.relative_to(path)): (p.read_bytes() if p.is_file() else None)
        for p in sorted(path.rglob("*"))
    }


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A finished 32-step navigation run (2 mm phantom, 50-step episodes)."""
    from typer.testing import CliRunner

    from sonogym.cli import app

    out = tmp_path_factory.mktemp("run") / "nav"
    args = ["train", "--task", "navigation", "--obs-mode", "us_heading", "--steps", "32",
            "--envs", "2", "--phantom-spacing", "2", "--env-option", "episode_length=50",
            "--checkpoint-every", "16", "--out", str(out)]  # fmt: skip
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture
def shipped(tiny_run, tmp_path, monkeypatch):
    """The tiny run exported as pretrained policy ``nav-test`` into a folder standing in for
    the package's own."""
    from sonogym.evaluation import pretrained as P

    root = tmp_path / "shipped"
    with warnings.catch_warnings():  # the tiny run was never evaluated: said, not needed here
        warnings.simplefilter("ignore")
        P.export_pretrained(tiny_run, "nav-test", root)
    monkeypatch.setattr(P, "PRETRAINED_DIR", root)
    return root


@pytest.fixture
def unwritable(tmp_path):
    """A folder nobody may create files in (a read-only folder; as root, /sys)."""
    if os.geteuid() != 0:
        folder = tmp_path / "read-only"
        folder.mkdir()
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    folder = Path("/sys")
    try:
        (folder / "sonogym-probe").touch()
    except OSError:
        yield folder
        return
    pytest.skip("no folder here refuses a new file")


# ----------------------------------------------------------------------------- export


def test_export_refuses_an_existing_policy_and_force_replaces_only_its_own_files(
    tiny_run, tmp_path, monkeypatch, capsys
):
    target = tmp_path / "D" / "navigation"
    args = ["export", "--run", tiny_run, "--name", "navigation", "--to", tmp_path / "D"]
    assert sonogym(monkeypatch, capsys, *args)[0] == 0
    (target / "notes.txt").write_text("my notes on this policy")
    before = tree(target)
    code, _, err = sonogym(monkeypatch, capsys, *args)
    line = one_line_error(code, err)
    assert "already holds pretrained policy 'navigation'" in line and "--force" in line
    assert "policy.safetensors" in line
    assert tree(target) == before  # nothing replaced, nothing deleted
    code, out, err = sonogym(monkeypatch, capsys, *args, "--force")
    assert code == 0, err
    assert (target / "notes.txt").read_text() == "my notes on this policy"
    assert "kept notes.txt" in err
    assert sorted(p.name for p in target.iterdir()) == sorted(
        ["config.json", "policy.safetensors", "model_card.json", "model_card.md", "notes.txt"]
    )


def test_export_into_the_packages_own_folder_needs_an_explicit_to(
    tiny_run, tmp_path, monkeypatch, capsys
):
    from sonogym.evaluation import pretrained as P

    package = tmp_path / "package-pretrained"
    shutil.copytree(P.PRETRAINED_DIR, package)
    monkeypatch.setattr(P, "PRETRAINED_DIR", package)
    before = tree(package)
    code, _, err = sonogym(monkeypatch, capsys, "export", "--run", tiny_run, "--name", "navigation")
    line = one_line_error(code, err)
    assert "--to" in line and str(package) in line
    assert tree(package) == before


def test_export_card_says_how_far_the_run_got_and_warns_of_no_evaluation(
    tiny_run, tmp_path, monkeypatch, capsys
):
    run = tmp_path / "stopped"
    shutil.copytree(tiny_run, run)
    for ckpt in (run / "checkpoints").glob("agent_*.pt"):
        ckpt.unlink()
    # interrupted at 30 % (a Ctrl-C checkpoint is named for the step it stopped at)
    shutil.copy(tiny_run / "checkpoints" / "agent_16.pt", run / "checkpoints" / "agent_10.pt")
    code, _, err = sonogym(monkeypatch, capsys, "export", "--run", run, "--name", "early", "--to",
                           tmp_path / "D")  # fmt: skip
    assert code == 0, err
    card = json.loads((tmp_path / "D" / "early" / "model_card.json").read_text())
    assert (card["steps_per_env"], card["planned_steps_per_env"]) == (10, 32)
    assert card["evaluations"] == {}
    md = (tmp_path / "D" / "early" / "model_card.md").read_text()
    assert "31 % of the 32 planned (the run stopped there)" in md
    assert "None: this checkpoint had not been evaluated" in md
    warnings = [line for line in err.splitlines() if line.startswith("warning:")]
    assert any("31 %" in w for w in warnings) and any("no evaluation" in w for w in warnings)


# ----------------------------------------------------------------------------- view


def test_a_failed_view_leaves_the_save_file_as_it_was_and_no_stub(tmp_path, monkeypatch, capsys):
    pytest.importorskip("rerun")
    mine = tmp_path / "mine.rrd"
    mine.write_bytes(b"RRF2\x00\x00\n\x07sonogym: an earlier view of the user's")
    before = mine.read_bytes()
    not_a_run = tmp_path / "notes"
    not_a_run.mkdir()
    code, _, err = sonogym(monkeypatch, capsys, "view", "--run", not_a_run, "--save", mine)
    assert mine.read_bytes() == before
    assert "is not a run folder" in one_line_error(code, err)
    fresh = tmp_path / "views" / "fresh.rrd"
    code, _, err = sonogym(monkeypatch, capsys, "view", "--run", not_a_run, "--save", fresh)
    assert code != 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.rrd", "notes"]  # no stub


def test_view_save_refuses_a_file_sonogym_did_not_write_unless_forced(
    tmp_path, monkeypatch, capsys
):
    pytest.importorskip("rerun")
    mine = tmp_path / "mine.rrd"
    mine.write_text("the user's own file, named .rrd")
    args = ["view", "--task", "navigation", "--steps", "1", "--phantom-spacing", "2", "--save",
            mine]  # fmt: skip
    code, _, err = sonogym(monkeypatch, capsys, *args)
    line = one_line_error(code, err)
    assert "not written by sonogym" in line and "--force" in line
    assert mine.read_text() == "the user's own file, named .rrd"
    code, out, err = sonogym(monkeypatch, capsys, *args, "--force")
    assert code == 0, err
    assert mine.read_bytes().startswith(b"RRF") and f"wrote {mine}" in out
    code, _, err = sonogym(monkeypatch, capsys, *args)  # now sonogym's own: replaced freely
    assert code == 0, err


@pytest.mark.parametrize("where", ["read-only folder", "parent is a file", "disk full"])
def test_view_save_to_an_impossible_path_is_one_line(where, tmp_path, monkeypatch, capsys, request):
    pytest.importorskip("rerun")
    if where == "read-only folder":
        save = request.getfixturevalue("unwritable") / "mine.rrd"
    elif where == "parent is a file":
        (tmp_path / "afile").write_text("x")
        save = tmp_path / "afile" / "mine.rrd"
    else:
        save = tmp_path / "mine.rrd"
        real = shutil.disk_usage
        monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=0))
    code, _, err = sonogym(monkeypatch, capsys, "view", "--task", "navigation", "--steps", "1",
                           "--phantom-spacing", "2", "--save", save)  # fmt: skip
    line = one_line_error(code, err)
    assert str(save) in line
    assert not save.exists()


def test_a_rerun_failure_to_create_the_file_is_one_line(tmp_path, monkeypatch, capsys):
    rr = pytest.importorskip("rerun")

    def refuse(self, path, *args, **kwargs):
        raise RuntimeError(f"Failed to create file: No space left on device (os error 28), {path}")

    monkeypatch.setattr(rr.RecordingStream, "save", refuse)
    save = tmp_path / "views" / "mine.rrd"
    code, _, err = sonogym(monkeypatch, capsys, "view", "--task", "navigation", "--steps", "1",
                           "--phantom-spacing", "2", "--save", save)  # fmt: skip
    assert "No space left on device" in one_line_error(code, err)
    assert not (tmp_path / "views").exists()


# ----------------------------------------------------------------------------- eval


def test_eval_pretrained_says_what_it_is_building_and_running(shipped, tmp_path, monkeypatch,
                                                              capsys):  # fmt: skip
    out = tmp_path / "D"
    code, stdout, err = sonogym(monkeypatch, capsys, "eval", "--pretrained", "nav-test",
                                "--patients", "0-1", "--trials", "2", "--envs", "2",
                                "--out", out)  # fmt: skip
    assert code == 0, err
    assert f"results go to {out}/" in err
    assert "building the navigation env: 2 patients to load" in err
    assert "navigation env: patients: 2/2 patient (100%)" in err
    for controller in ("policy", "expert", "random"):
        assert f"{controller} (2 episodes): " in err
    assert "episodes done=2/2" in err
    assert (out / "eval-custom.json").is_file() and "| policy |" in stdout


def test_ctrl_c_during_eval_says_what_was_kept_and_leaves_nothing(
    shipped, tmp_path, monkeypatch, capsys
):
    from sonogym.evaluation import rl_eval

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(rl_eval, "run_controllers", interrupted)
    out = tmp_path / "D"
    code, _, err = sonogym(monkeypatch, capsys, "eval", "--pretrained", "nav-test", "--trials",
                           "2", "--envs", "2", "--out", out)  # fmt: skip
    assert code == 130
    assert one_line_error(code, err) == "sonogym: interrupted: nothing was written"
    assert not out.exists()


@pytest.mark.parametrize("bad", ["/nonexistent/subject", f"{SUBJECT}@abc"])
def test_a_failed_eval_pretrained_leaves_no_folder(bad, shipped, tmp_path, monkeypatch, capsys):
    out = tmp_path / "D"
    code, _, err = sonogym(monkeypatch, capsys, "eval", "--pretrained", "nav-test", "--patients",
                           bad, "--trials", "2", "--envs", "2", "--out", out)  # fmt: skip
    assert not out.exists()
    one_line_error(code, err)


def test_a_bad_variant_index_is_called_that(shipped, tmp_path, monkeypatch, capsys):
    code, _, err = sonogym(monkeypatch, capsys, "eval", "--pretrained", "nav-test", "--patients",
                           f"{SUBJECT}@abc", "--out", tmp_path / "D")  # fmt: skip
    line = one_line_error(code, err)
    assert "'abc' is not a variant index" in line and "does not exist" not in line


def test_eval_out_a_file_names_the_file_not_an_internal_function(
    shipped, tmp_path, monkeypatch, capsys
):
    afile = tmp_path / "results.txt"
    afile.write_text("a user's file")
    code, _, err = sonogym(monkeypatch, capsys, "eval", "--pretrained", "nav-test", "--trials",
                           "2", "--out", afile)  # fmt: skip
    line = one_line_error(code, err)
    assert f"{afile}: it is a file, not a folder" in line and "--out" in line
    assert "evaluate_run" not in line and "(" not in line.split("is a file")[0]
    assert afile.read_text() == "a user's file"


# ----------------------------------------------------------------------------- messages


def test_a_users_folder_at_a_run_path_is_not_called_a_run(tmp_path, monkeypatch, capsys):
    folder = tmp_path / "runs" / "nav-ppo-small-s0"  # where `reproduce navigation` trains
    folder.mkdir(parents=True)
    (folder / "notes.txt").write_text("my notes")
    code, _, err = sonogym(monkeypatch, capsys, "train", "--task", "navigation", "--steps", "4",
                           "--envs", "1", "--out", folder)  # fmt: skip
    line = one_line_error(code, err)
    assert "is not a `sonogym train` run" in line and "notes.txt" in line
    assert "already holds" not in line and "--resume" not in line
    assert tree(folder) == {"notes.txt": b"my notes"}


def test_a_boolean_env_option_says_it_is_a_switch(tmp_path, monkeypatch, capsys):
    code, _, err = sonogym(monkeypatch, capsys, "train", "--task", "navigation", "--env-option",
                           "imaging_randomization=maybe", "--out", tmp_path / "r")  # fmt: skip
    line = one_line_error(code, err)
    assert "imaging_randomization" in line and "true or false" in line
    assert "number" not in line
    assert not (tmp_path / "r").exists()


# ----------------------------------------------------------------------------- morphometry


@pytest.fixture
def no_measuring(monkeypatch):
    """Fail the test if morphometry starts measuring (loading the subject or a phantom)."""
    from sonogym.anatomy import totalseg
    from sonogym.viz import morphometry

    def measured(*args, **kwargs):
        raise AssertionError("morphometry measured before checking its options")

    monkeypatch.setattr(totalseg, "load_totalsegmentator", measured)
    monkeypatch.setattr(morphometry, "measure_population", measured)
    monkeypatch.setattr("sonogym.anatomy.load_totalsegmentator", measured)


def test_morphometry_checks_its_options_before_measuring(
    no_measuring, tmp_path, monkeypatch, capsys
):
    out = tmp_path / "M"
    code, _, err = sonogym(monkeypatch, capsys, "morphometry", "--spacing", "5", "--out", out)
    assert "--spacing 5" in one_line_error(code, err)
    page = tmp_path / "page.md"
    page.write_text("# A page without the marks\n")
    code, _, err = sonogym(monkeypatch, capsys, "morphometry", "--doc", page, "--out", out)
    assert "no morphometry marks" in one_line_error(code, err)
    assert not out.exists()


def test_a_failed_morphometry_leaves_no_out_folder(tmp_path, monkeypatch, capsys):
    def unreadable(*args, **kwargs):
        raise ValueError("the subject's CT could not be read")

    monkeypatch.setattr("sonogym.anatomy.load_totalsegmentator", unreadable)
    out = tmp_path / "M"
    code, _, err = sonogym(monkeypatch, capsys, "morphometry", "--seeds", "1", "--out", out)
    assert "could not be read" in one_line_error(code, err)
    assert not out.exists()


# ----------------------------------------------------------------------------- outside a checkout


def test_morphometry_outside_a_checkout_reads_the_shipped_subject_and_says_where_it_writes(
    tmp_path, monkeypatch, capsys
):
    from sonogym.viz import morphometry

    seen = {}

    def report(out, subject, *args, **kwargs):
        seen["subject"] = Path(subject)
        return {}

    monkeypatch.setattr(morphometry, "write_report", report)
    monkeypatch.chdir(tmp_path)  # no tests/data here
    code, out, err = sonogym(monkeypatch, capsys, "morphometry", "--out", "M")
    assert code == 0, err
    assert (seen["subject"] / "ct.nii.gz").is_file()
    assert seen["subject"].parent.name == "data" and "tests" not in seen["subject"].parts
    assert f"writing to {tmp_path / 'M'}/" in out.splitlines()[0]
    for given in ("tests/data/totalsegmentator_example", "totalsegmentator_example"):
        code, _, err = sonogym(monkeypatch, capsys, "morphometry", "--subject", given)
        assert code == 0, err
        assert seen["subject"] == Path(morphometry.__file__).parents[1] / "data" / SUBJECT.name


def test_reproduce_writes_only_under_root_and_says_so(tmp_path, monkeypatch, capsys):
    from sonogym import reproduce_root

    ran = []

    def child(argv):
        ran.append((Path.cwd(), argv[3:]))
        return 0

    monkeypatch.setattr(reproduce_root, "run_command", child)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    root = tmp_path / "R"
    code, out, err = sonogym(monkeypatch, capsys, "reproduce", "reconstruction", "--root", root)
    assert code == 0, err
    assert f"outputs under {root}/" in out.splitlines()[0]
    assert [cwd for cwd, _ in ran] == [root] * 3 and ran[0][1][0] == "train"
    assert list(elsewhere.iterdir()) == [] and Path.cwd() == elsewhere


def test_the_recipes_real_subject_ships_with_the_package(tmp_path, monkeypatch):
    from sonogym.envs.options import parse_patients

    monkeypatch.chdir(tmp_path)  # no tests/data here
    (given,) = parse_patients(["tests/data/totalsegmentator_example"])
    assert Path(given).is_dir() and Path(given).parent.name == "data"
    assert sorted(p.name for p in (Path(given) / "segmentations").iterdir()) == sorted(
        p.name for p in (SUBJECT / "segmentations").iterdir()
    )
    assert parse_patients(["tests/data/totalsegmentator_example@2"]) == (f"{given}@2",)


def test_usage_errors_are_one_line(monkeypatch, capsys):
    code, _, err = sonogym(monkeypatch, capsys, "export", "--bogus")
    assert "--bogus" in one_line_error(code, err)


def test_ctrl_c_in_reproduce_lets_the_running_command_stop_in_order(monkeypatch):
    """subprocess.run killed a command 0.25 s after Ctrl-C, before a training run had saved its
    checkpoint: the command (which had the terminal's Ctrl-C too) is waited for instead."""
    from sonogym import reproduce_root
    from sonogym.outputs import CommandInterrupted

    class Child:  # a training run that needs a few seconds to save after Ctrl-C
        signals: list = []
        waits = 0

        def __init__(self, argv):
            pass

        def wait(self, timeout=None):
            Child.waits += 1
            if Child.waits == 1:
                raise KeyboardInterrupt  # the user's Ctrl-C, while the parent waits
            return 130  # saved its checkpoint and stopped, within the grace time

        def send_signal(self, sig):
            Child.signals.append(sig)

    monkeypatch.setattr(reproduce_root.subprocess, "Popen", Child)
    argv = [sys.executable, "-m", "sonogym.cli", "train", "--task", "navigation"]
    with pytest.raises(CommandInterrupted, match="stopped `sonogym train --task navigation`"):
        reproduce_root.run_command(argv)
    assert Child.signals == [] and Child.waits == 2  # waited, neither signalled nor killed
