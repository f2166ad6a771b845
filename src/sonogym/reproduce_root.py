"""Where ``sonogym reproduce`` works: its ``--root`` folder, and its commands' Ctrl-C.

A recipe's commands name their outputs relative to one folder (``runs/...``,
``docs/results/...``, ``reports/paper/...``), and their input data by its checkout path
(``tests/data/totalsegmentator_example``, which the commands read from the package's copy where
no such path exists: ``sonogym.package_data``). ``working_in(root)`` runs the recipe from
``root``, so a reproduction writes only there, from a checkout or an installed package alike.
``run_command`` runs one of its commands as a child process and, on Ctrl-C, waits for the child
to stop in order (a training run saves its checkpoint) before saying what was kept.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from sonogym.outputs import CommandInterrupted, check_folder

#: Seconds a command is given to stop on its own after Ctrl-C (it had the signal too), then
#: after being sent SIGINT, before it is killed.
GRACE_S = (10.0, 60.0)


@contextlib.contextmanager
def working_in(root: str | Path, create: bool = True) -> Iterator[Path]:
    """Run the block from folder ``root`` (made if absent and ``create``; refused with one line
    if it cannot be written); the process's folder and ``PYTHONPATH`` (its entries made
    absolute, so that the recipe's child processes import the same sonogym) are restored
    after. Without ``create``, an absent ``root`` (nothing done there yet) is stood in for by an
    empty temporary folder. A ``root`` this made and left empty is removed."""
    root = check_folder(Path(root).absolute(), "--root")
    before, env = Path.cwd(), os.environ.get("PYTHONPATH")
    made = not root.exists()
    with contextlib.ExitStack() as stack:
        if made and not create:
            where = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        else:
            root.mkdir(parents=True, exist_ok=True)
            where = root
        if env:
            os.environ["PYTHONPATH"] = os.pathsep.join(
                str(Path(p).absolute()) for p in env.split(os.pathsep) if p
            )
        os.chdir(where)
        try:
            yield root
        finally:
            os.chdir(before)
            if env is not None:
                os.environ["PYTHONPATH"] = env
            if made and create and root.is_dir() and not any(root.iterdir()):
                root.rmdir()


def run_command(argv: list[str]) -> int:
    """Run one recipe command (``[python, -m, sonogym.cli, ...]``) to its end; its exit status.
    Ctrl-C waits for the command to stop (``GRACE_S``) and raises ``CommandInterrupted``."""
    child = subprocess.Popen(argv)
    try:
        return child.wait()
    except KeyboardInterrupt:
        _stop(child)
        trained = " (an interrupted training run saves a checkpoint)" if "train" in argv[3] else ""
        raise CommandInterrupted(
            f"stopped `sonogym {' '.join(argv[3:])}`{trained}; the finished commands' outputs "
            f"are kept in {Path.cwd()}; run the same sonogym reproduce again to resume"
        ) from None


def _stop(child: subprocess.Popen) -> None:
    """Let a child that had the terminal's Ctrl-C finish stopping; send it SIGINT if it did
    not get one; kill it only if it still runs after that."""
    for grace, then in zip(GRACE_S, (signal.SIGINT, signal.SIGKILL), strict=True):
        try:
            child.wait(timeout=grace)
            return
        except subprocess.TimeoutExpired:
            child.send_signal(then)
        except KeyboardInterrupt:  # a second Ctrl-C: stop waiting politely
            child.send_signal(then)
    child.wait()
