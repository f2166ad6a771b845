"""Folders and files that must not be lost: the one rule for output folders and atomic writes.

Every command that writes a run, a dataset, a sweep or a subject folder (``train``,
``il-train``, ``record``, ``sweep``, ``phantom``) follows ``prepare_output``: a new or empty
folder is used and marked as the command's (a ``.sonogym`` file naming its kind and command);
an existing one is continued only with ``resume`` and replaced only with ``force``, which
deletes only a folder carrying that marker and holding nothing but what the command writes
(and says what it deleted). While a command writes a folder it holds the folder's lock
(``OutputLock``), so a second process cannot write into it at the same time.

Files that matter (checkpoints, ``config.json``, caches, datasets, reports) are written to a
temporary file in the same folder and renamed over the target, so a killed process leaves
either the old file or the new one, never a torn one.

A training run's folder, RL (``sonogym train``) or IL (``sonogym il-train``), is read through
one ``RunFolder``: its config, its checkpoints (oldest first), the newest one that reads. What
differs between the two (checkpoint names, the checkpoint and config readers, how config.json
marks the kind) is a ``RunKind``, defined beside each trainer (``agents.checkpoint.RL_RUN``,
``imitation.run.IL_RUN``); this module imports neither.
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shutil
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO


class OutputExistsError(FileExistsError):
    """An output folder already holds something; the message says how to continue or replace."""


class CheckpointError(ValueError):
    """A checkpoint file cannot be read; the message names it and says what to do."""


def load_weights(path: str | Path, device: Any = "cpu", what: str = "checkpoint") -> Any:
    """``torch.load(path, weights_only=True)``: tensors, numbers, strings and containers, never
    pickled code; a missing file raises ``FileNotFoundError``, an empty, truncated or foreign
    one ``CheckpointError`` naming it (``what``: the kind of file, for the message)."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} not found")
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # truncated, empty, not a torch file, or pickled objects
        detail = str(e).splitlines()[0] if str(e) else "no detail"
        raise CheckpointError(
            f"{path} is not a readable {what} ({type(e).__name__}: {detail}); pick another "
            "with --checkpoint, or resume from an earlier one"
        ) from None


class TrainingInterrupted(Exception):
    """Ctrl-C during training (RL or IL): a checkpoint was saved; the message says how to
    resume."""


#: The marker file every output folder sonogym creates holds: JSON with the folder's ``kind``
#: and the ``command`` that writes it. ``--force`` deletes only folders it marks.
MARKER = ".sonogym"
#: The lock file of an output folder in use (``OutputLock``).
LOCK = ".sonogym.lock"
#: The acting weights in a shipped policy's folder (``sonogym.evaluation.pretrained``).
SHIPPED_WEIGHTS = "policy.safetensors"
#: What ``sonogym eval`` writes into a run folder.
_EVAL_ENTRIES = (
    "eval.json",
    "eval.md",
    "eval-*.json",
    "eval-*.md",
    "episodes",
    "trajectories-*.png",
)


@dataclass(frozen=True)
class FolderKind:
    what: str  # what the folder holds, for messages
    command: str  # the command that creates it
    entries: tuple[str, ...]  # the top-level names it writes (glob patterns)


#: The kinds of output folder and what each holds: ``--force`` deletes these entries and
#: refuses a folder that holds anything else.
KINDS: dict[str, FolderKind] = {
    "rl-run": FolderKind(
        "`sonogym train` run",
        "sonogym train",
        ("config.json", "checkpoints", "events.out.tfevents.*", *_EVAL_ENTRIES),
    ),
    "il-run": FolderKind(
        "`sonogym il-train` run",
        "sonogym il-train",
        ("config.json", "checkpoints", "tb", *_EVAL_ENTRIES),
    ),
    "dataset": FolderKind("dataset", "sonogym record", ("meta", "data")),
    "sweep": FolderKind(
        "sweep", "sonogym sweep", ("sweep.json", "sweep.md", "sweep.csv", "runs", "tune", "plots")
    ),
    "subject": FolderKind(
        "subject folder",
        "sonogym phantom",
        ("ct.nii.gz", "segmentations", "combined_label_map.nii.gz", "sonogym.json", "preview.png"),
    ),
}


class OutputInUseError(OutputExistsError):
    """Another process is writing the output folder (it holds the folder's lock)."""


class OutputLock:
    """An exclusive lock on an output folder while one process writes it: ``fcntl.flock`` on
    ``<folder>/.sonogym.lock``, which the OS releases when the process ends however it ends
    (SIGKILL included), so a crashed run never leaves a stale lock. The file holds the
    owner's pid for the refusal message. Two ``OutputLock`` objects exclude each other even
    within one process."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK
        self._fd: int | None = None

    def acquire(self) -> OutputLock:
        """Take the lock (creating the folder); ``OutputInUseError`` naming the folder and the
        holder's pid if another process (or ``OutputLock``) holds it."""
        try:
            import fcntl
        except ImportError:  # no flock on this platform: folders are not locked
            return self
        self.folder.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                raise OutputInUseError(
                    f"{self.folder} is in use by another sonogym process (pid {holder}), which "
                    "holds its lock; wait for it to finish (or stop it), or choose another "
                    "output folder"
                ) from None
            # a lock file removed and recreated between open and flock is not the folder's
            try:
                current = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                current = False
            if current:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases the flock
            self._fd = None


@dataclass
class PreparedOutput:
    """An output folder ready for writing (``prepare_output``), locked until ``release``
    (or the end of a ``with`` block)."""

    path: Path
    resumed: bool  # an existing folder is being continued
    deleted: tuple[str, ...]  # what --force deleted (top-level names, folders with "/")
    fresh: bool  # the folder was absent or empty
    created: bool  # the folder was absent
    lock: OutputLock

    def release(self, failed: bool = False) -> None:
        """Unlock; with ``failed``, a fresh folder that still holds nothing but the marker and
        the lock is left as it was found (a refusal leaves nothing behind)."""
        self.lock.release()
        if failed and self.fresh and not output_entries(self.path):
            for name in (MARKER, LOCK):
                (self.path / name).unlink(missing_ok=True)
            if self.created:
                try:
                    self.path.rmdir()
                except OSError:
                    pass

    def __enter__(self) -> PreparedOutput:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.release(failed=exc_type is not None)


def output_entries(path: str | Path) -> list[Path]:
    """The folder's entries besides sonogym's marker and lock (what makes it non-empty)."""
    path = Path(path)
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if p.name not in (MARKER, LOCK))


def read_marker(path: str | Path) -> dict | None:
    """The folder's marker (``{"kind", "command", ...}``), or None if it has none or an
    unreadable one."""
    f = Path(path) / MARKER
    try:
        marker = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    return marker if isinstance(marker, dict) and isinstance(marker.get("kind"), str) else None


def write_marker(path: str | Path, kind: str) -> None:
    """Mark ``path`` as a folder of ``kind`` written by this sonogym."""
    import time

    import sonogym

    atomic_write_json(Path(path) / MARKER, {
        "kind": kind,
        "command": KINDS[kind].command,
        "sonogym": getattr(sonogym, "__version__", "unknown"),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    })  # fmt: skip


def _kind(kind: str) -> FolderKind:
    if kind not in KINDS:
        raise ValueError(f"unknown output folder kind {kind!r}; known: {sorted(KINDS)}")
    return KINDS[kind]


def _owned(name: str, kind: str) -> bool:
    """Whether a top-level entry ``name`` is one that ``kind`` writes (or its temporary)."""
    base = _TEMPORARY.sub("", name)
    return any(fnmatch.fnmatchcase(base, pattern) for pattern in KINDS[kind].entries)


def _other_kind(path: Path, kind: str) -> str | None:
    """A refusal if ``path``'s marker says it is a folder of another kind, else None."""
    marker = read_marker(path)
    if marker is None or marker["kind"] == kind:
        return None
    other = KINDS.get(marker["kind"])
    if other is None:  # a kind of a newer sonogym
        held = f"a {marker['kind']!r} folder"
    elif other.command in other.what:
        held = f"a {other.what}"
    else:
        held = f"a {other.what} (written by {other.command})"
    return f"{path} holds {held}, not a {KINDS[kind].what}; choose another output folder"


def clear_output(path: str | Path, kind: str) -> list[str]:
    """Delete what a folder of ``kind`` holds, for ``--force``; returns what went (names
    relative to ``path``, folders with "/"). Refused (``OutputExistsError``, nothing deleted)
    unless the folder carries sonogym's marker of that kind and holds only entries that kind
    writes: a folder that is not one of ours, or that holds the user's own files, is never
    deleted."""
    deleted = []
    for p in _clearable(Path(path), kind):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
            deleted.append(p.name + "/")
        else:
            p.unlink()
            deleted.append(p.name)
    return deleted


def _clearable(path: Path, kind: str) -> list[Path]:
    """The entries ``clear_output`` would delete; its refusals, without deleting anything."""
    spec = _kind(kind)
    if read_marker(path) is None:
        raise OutputExistsError(
            f"{path} is not empty and carries no {MARKER} marker: it was not written by "
            f"{spec.command}, or by a version from before folders were marked, and --force "
            "deletes only folders sonogym marked as its own; refusing to delete it. Delete it "
            "by hand if nothing in it is needed, or choose another output folder"
        )
    other = _other_kind(path, kind)
    if other:
        raise OutputExistsError(other + "; refusing to delete it")
    entries = output_entries(path)
    foreign = [p.name + ("/" if p.is_dir() and not p.is_symlink() else "") for p in entries
               if not _owned(p.name, kind)]  # fmt: skip
    if foreign:
        raise OutputExistsError(
            f"{path} holds {', '.join(foreign)}, which {spec.command} does not write; refusing "
            f"to delete the {spec.what}. Move them out of it (or delete the folder by hand), "
            "or choose another output folder"
        )
    return entries


def deleted_message(path: str | Path, deleted: tuple[str, ...] | list[str]) -> str:
    """The line a command prints after ``--force`` replaced ``path``."""
    return f"--force: deleted {', '.join(deleted)} from {path}"


def prepare_output(path: str | Path, resume: bool, force: bool, kind: str) -> PreparedOutput:
    """Apply the output-folder rule to ``path`` and lock it (``OutputLock``) for the caller,
    who releases it (``with prepare_output(...)``, or ``.release()``).

    * absent or empty (nothing but sonogym's marker and lock): created and marked with
      ``kind`` (``MARKER``);
    * ``resume``: an existing folder is continued (one marked as another kind is refused);
    * ``force``: an existing folder is emptied by ``clear_output`` (only a folder marked as
      ``kind`` that holds only what ``kind`` writes; ``.deleted`` lists what went);
    * otherwise an existing folder is refused, saying how to continue or replace it.

    A folder another process is writing is refused (``OutputInUseError``, naming its pid); in
    a folder without sonogym's marker the other checks come first, so that a refusal writes
    nothing (not even the lock file)."""
    path = Path(path)
    spec = _kind(kind)
    if resume and force:
        raise ValueError("give --resume (continue) or --force (replace), not both")

    def check() -> bool:  # read-only; True if the folder is empty or absent
        if path.exists() and not path.is_dir():
            raise OutputExistsError(
                f"{path} exists and is not a folder; choose another output path"
            )
        other = _other_kind(path, kind) if path.is_dir() else None
        if not output_entries(path):
            if resume:
                raise FileNotFoundError(f"nothing to resume: {path} does not hold a {spec.what}")
            return True
        if other:
            raise OutputExistsError(other)
        foreign = [p.name + ("/" if p.is_dir() else "") for p in output_entries(path)
                   if not _owned(p.name, kind)]  # fmt: skip
        if not (resume or force) and foreign and read_marker(path) is None:
            raise OutputExistsError(
                f"{path} is not a {spec.what}: it holds {_some(foreign)}, which "
                f"{spec.command} does not write, and no {MARKER} marker; choose another output "
                "folder, or move those files out of it"
            )
        if not (resume or force):
            raise OutputExistsError(
                f"{path} already holds a {spec.what}; pass --resume to continue it or --force "
                "to replace it (or choose another output folder)"
            )
        if force:
            _clearable(path, kind)
        return False

    if not (path.is_dir() and read_marker(path) is not None):
        check()  # not (yet) ours: a refusal writes nothing into it, not even the lock file
    existed = path.exists()
    lock = OutputLock(path).acquire()
    out = PreparedOutput(path, resume, (), not output_entries(path), not existed, lock)
    try:
        out.fresh = check()  # again, under the lock: another process may have written meanwhile
        if force and not out.fresh:
            out.deleted = tuple(clear_output(path, kind))
        if out.fresh or force:
            write_marker(path, kind)
    except BaseException:
        out.release(failed=True)
        raise
    return out


def _some(names: list[str], most: int = 5) -> str:
    """The first ``most`` names, joined, and how many more."""
    shown = ", ".join(names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")


_TEMPORARY = re.compile(r"\.tmp(\d+)$")


def temporary_path(path: Path) -> Path:
    """Where ``path`` is written before its rename: ``<name>.tmp<pid>`` beside it (globs for
    ``*.parquet``, ``*.pt``, ``*.json`` never see it)."""
    return path.with_name(f"{path.name}.tmp{os.getpid()}")


def atomic_write(path: str | Path, write: Callable[[BinaryIO], Any]) -> Path:
    """``write(file)`` into ``temporary_path(path)``, fsync, then rename it over ``path``
    (parent folders are created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(path)
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    return atomic_write(path, lambda f: f.write(data))


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    # ASCII with escapes: a path that is not valid UTF-8 (surrogate-escaped by Python) round
    # trips as \udcXX instead of failing to encode
    return atomic_write_text(path, json.dumps(obj, indent=indent, ensure_ascii=True) + "\n")


def atomic_torch_save(obj: Any, path: str | Path) -> Path:
    """``torch.save`` through a temporary file and a rename."""
    import torch

    return atomic_write(path, lambda f: torch.save(obj, f))


def remove_stale_temporaries(folder: str | Path, recursive: bool = False) -> int:
    """Delete ``*.tmp<pid>`` files in ``folder`` whose writer process no longer exists (a killed
    write's leftovers; a live writer's file is left alone). Returns how many went."""
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    removed = 0
    for f in folder.rglob("*") if recursive else folder.iterdir():
        m = _TEMPORARY.search(f.name)
        if m is None or not f.is_file() or int(m.group(1)) == os.getpid():
            continue
        try:
            os.kill(int(m.group(1)), 0)
        except ProcessLookupError:  # the writer is dead: its file will never be renamed
            f.unlink(missing_ok=True)
            removed += 1
        except (PermissionError, OverflowError, OSError):
            pass  # alive (another user's) or not a pid we can ask about: leave it
    return removed


def read_json(path: str | Path, what: str, required: tuple[str, ...] = ()) -> dict:
    """A JSON object from ``path``, with a clear error for a missing, malformed or incomplete
    file (``required``: top-level keys it must have)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: is {path.parent} a {what}?")
    try:
        obj = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(
            f"{path} is not valid JSON ({e}); restore it or recreate the {what}"
        ) from None
    if not isinstance(obj, dict):
        raise ValueError(f"{path} must hold a JSON object, not {type(obj).__name__}")
    missing = [k for k in required if k not in obj]
    if missing:
        raise ValueError(f"{path} lacks {missing}: it was not written by this {what} writer")
    return obj


def to_jsonable(obj: Any) -> Any:
    """Dataclasses, paths, tuples -> JSON-serialisable values (for configs written to disk)."""
    import dataclasses

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, int | float | str | bool) or obj is None:
        return obj
    return repr(obj)


def lists_to_tuples(x: Any) -> Any:
    """JSON lists back to the tuples configs hold, recursively (dict values too)."""
    if isinstance(x, list | tuple):
        return tuple(lists_to_tuples(v) for v in x)
    if isinstance(x, dict):
        return {k: lists_to_tuples(v) for k, v in x.items()}
    return x


# ----------------------------------------------------------------------------- run folders


@dataclass(frozen=True)
class RunKind:
    """What sets one kind of training run's folder apart (see the module doc)."""

    name: str  # "rl" | "il"
    command: str  # the command that writes such runs, for messages
    marker: str | None  # config.json's "kind" for such runs; None: a config.json without one
    checkpoint_name: str  # regex of a checkpoint's file name in checkpoints/; group 1: step
    checkpoint_hint: str  # the file names as messages show them, e.g. "agent_<t>.pt"
    read_checkpoint: Callable[[Path, Any], Any]  # (path, device) -> state; an unreadable
    # file raises CheckpointError (or OSError), a missing one FileNotFoundError
    read_config: Callable[[Path], dict]  # run folder -> config.json, checked as evaluation
    # needs it (a clear error naming the file otherwise)
    env_kwargs_key: tuple[str, ...]  # where config.json holds the training env's options

    def step_of(self, path: str | Path) -> int | None:
        """The step in a checkpoint's file name, read from the name's end (a renamed copy
        with a prefix keeps it); None for a name of another pattern."""
        m = re.search(f"{self.checkpoint_name}$", Path(path).name)
        return int(m.group(1)) if m else None

    def env_kwargs(self, config: dict) -> dict:
        """The env options a run of this kind was trained on ({} where none are recorded)."""
        for key in self.env_kwargs_key:
            config = config.get(key, {})
        return config


@dataclass(frozen=True)
class Checkpoint:
    step: int  # from the file name: env steps per env (RL) or optimiser steps (IL)
    path: Path
    state: Any  # what the kind's reader returned


@dataclass(frozen=True)
class RunFolder:
    """A training run's folder as the kind ``kind`` lays it out."""

    path: Path
    kind: RunKind

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))  # a str path is taken too

    def config(self) -> dict:
        """The run's config.json, checked (``RunKind.read_config``)."""
        return self.kind.read_config(self.path)

    def checkpoints(self) -> list[tuple[int, Path]]:
        """(step, path) of every checkpoint in ``checkpoints/``, oldest first."""
        folder = self.path / "checkpoints"
        names = re.compile(self.kind.checkpoint_name)
        found = [p for p in folder.glob("*") if names.fullmatch(p.name)] if folder.is_dir() else []
        return sorted((self.kind.step_of(p), p) for p in found)

    def newest_readable_checkpoint(
        self, device: Any = "cpu", warn: Callable[[str], None] | None = None
    ) -> Checkpoint | None:
        """The newest checkpoint that reads, or None; each unreadable newer one (a save killed
        half-way, a corrupt file) is skipped with a warning naming it (``warn``: a callable
        taking the message; default ``warnings.warn``)."""
        for step, path in reversed(self.checkpoints()):
            try:
                return Checkpoint(step, path, self.kind.read_checkpoint(path, device))
            except (CheckpointError, OSError) as e:
                msg = f"skipping unreadable checkpoint: {e}"
                if warn is None:
                    warnings.warn(msg, stacklevel=2)
                else:
                    warn(msg)
        return None

    def require_checkpoint(
        self, device: Any = "cpu", warn: Callable[[str], None] | None = None
    ) -> Checkpoint:
        """``newest_readable_checkpoint``, or ``FileNotFoundError`` naming the folder."""
        found = self.newest_readable_checkpoint(device, warn)
        if found is None:
            raise FileNotFoundError(
                f"no readable checkpoints/{self.kind.checkpoint_hint} in {self.path}"
            )
        return found


def open_run(path: str | Path, kinds: Sequence[RunKind]) -> RunFolder:
    """The run folder at ``path`` as the one of ``kinds`` its config.json marks (its "kind";
    the kind without a marker for a config.json without one); a missing or malformed
    config.json is named."""
    path = Path(path)
    what = " / ".join(f"`{k.command}`" for k in kinds) + " run folder"
    config = read_json(path / "config.json", what, ("task",))
    marker = config.get("kind")
    kind = next((k for k in kinds if k.marker == marker), None)
    if kind is None:
        kind = next(k for k in kinds if k.marker is None)
    return RunFolder(path, kind)
