"""Output files and folders of the commands that write one result (``view --save``, ``eval
--out``, ``export --to``, ``morphometry --out``, ``reproduce --root``); run, dataset, sweep and
subject folders follow ``sonogym.runs.prepare_output`` instead.

* ``check_folder`` / ``check_file``, before the work starts: an output that cannot be written
  (a folder nobody may write in, a parent that is a file, a file where a folder is asked or a
  folder where a file is, a disk with no space left) is refused with one line naming it, and
  nothing is created. ``check_file`` also refuses to replace a file the project did not write
  unless ``force``.
* ``undo_on_failure``, around the work: what the command creates (folders and files absent when
  it started) is removed again when it fails, so a failed command leaves nothing of its own
  behind; Ctrl-C becomes ``CommandInterrupted``, whose message says what was kept.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

#: Free space (bytes) below which an output's disk counts as full.
MIN_FREE_BYTES = 1 << 20


class OutputPathError(ValueError):
    """An output path that cannot be written; the message names it and what to do."""


class CommandInterrupted(Exception):
    """Ctrl-C stopped a command; the message says what it removed and what was kept."""


def _existing_ancestor(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (the folder a new output is made in)."""
    path = path.absolute()
    for p in (path, *path.parents):
        if p.exists():
            return p
    return Path(path.anchor)


def check_folder(path: str | Path, what: str = "output folder", fix: str = "") -> Path:
    """``path`` as a folder an output can be written to: one that exists, or can be made under
    its nearest existing ancestor. Writes nothing: a probe file is made and removed at once in
    the folder that exists. ``OutputPathError`` otherwise, naming why and ending with ``fix``
    (default: give another folder)."""
    path = Path(path)
    fix = fix or "give a folder you can write to"
    if path.exists() and not path.is_dir():
        raise OutputPathError(f"{what} {path}: it is a file, not a folder; {fix}")
    problem = _unwritable(path)
    if problem:
        raise OutputPathError(f"{what} {path}: {problem}; {fix}")
    return path


def check_file(
    path: str | Path,
    what: str = "output file",
    force: bool = False,
    ours: Callable[[Path], bool] | None = None,
) -> Path:
    """``path`` as a file an output can be written to: not a folder, in a folder that exists
    or can be made, and can be written (as ``check_folder``). An existing file that ``ours``
    says the project did not write is refused unless ``force``."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"{what} {path} is a folder; give a file name")
    problem = _unwritable(path.parent)
    if problem:
        raise OutputPathError(f"{what} {path}: {problem}; give a file in a folder you can write to")
    if path.exists() and ours is not None and not force and not ours(path):
        raise OutputPathError(
            f"{what} {path} already exists and was not written by sonogym; pass --force to "
            "replace it, or give another file name"
        )
    return path


def _unwritable(folder: Path) -> str:
    """Why no file can be written in ``folder`` (made if absent), or "" if one can."""
    base = _existing_ancestor(folder)
    if not base.is_dir():
        return f"{base} is a file, so no folder can be made under it"
    try:
        with tempfile.TemporaryFile(dir=base):
            pass
        free = shutil.disk_usage(base).free
    except OSError as e:
        return f"no file can be made in {base} ({e.strerror or e})"
    if free < MIN_FREE_BYTES:
        return f"the disk holding {base} is full ({free} bytes free)"
    return ""


def _created_root(path: Path) -> Path | None:
    """The outermost of ``path`` and its ancestors that does not exist (what writing ``path``
    would create), or None if ``path`` exists."""
    path = path.absolute()
    if path.exists() or path.is_symlink():
        return None
    missing = path
    for parent in path.parents:
        if parent.exists():
            break
        missing = parent
    return missing


def _remove(paths: list[Path]) -> list[Path]:
    """Delete what was created (files, folders with all in them); returns what went."""
    gone = []
    for p in paths:
        try:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            elif p.exists() or p.is_symlink():
                p.unlink()
            else:
                continue  # never made
        except OSError:
            continue  # the failure's own message matters more than this one
        gone.append(p)
    return gone


@contextlib.contextmanager
def undo_on_failure(
    *paths: str | Path, temporary: tuple[str | Path, ...] = (), kept: str = ""
) -> Iterator[None]:
    """Around a command's work: of ``paths`` (the outputs it may write) and ``temporary`` (its
    scratch files), those absent now, and the absent folders above them, are deleted if the
    block raises, so that a failed command leaves nothing it created. Ctrl-C is re-raised as
    ``CommandInterrupted``, naming what was removed (scratch files are not named) and
    ``kept`` (what the caller keeps, e.g. the finished part of a longer job)."""
    created: list[Path] = []
    for p in (*paths, *temporary):
        root = _created_root(Path(p))
        if root is not None and root not in created:
            created.append(root)
    scratch = {Path(p).absolute() for p in temporary}
    try:
        yield
    except KeyboardInterrupt:
        gone = [p for p in _remove(created) if p not in scratch]
        said = [f"removed {', '.join(map(str, gone))}" if gone else "nothing was written"]
        raise CommandInterrupted("; ".join(said + ([kept] if kept else []))) from None
    except BaseException:
        _remove(created)
        raise
