"""Folders and files that must not be lost: the one rule for output folders and atomic writes.

Every command that writes a run, a dataset, a sweep or a subject folder (``train``,
``il-train``, ``record``, ``sweep``, ``phantom``) follows ``prepare_output``: a new or empty
folder is used as it is; an existing one is continued only with ``resume`` and replaced only
with ``force``. Files that matter (checkpoints, ``config.json``, caches, datasets, reports) are
written to a temporary file in the same folder and renamed over the target, so a killed process
leaves either the old file or the new one, never a torn one.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable
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


def prepare_output(
    path: str | Path, resume: bool, force: bool, what: str = "run", marker: str | None = None
) -> bool:
    """Apply the output-folder rule to ``path``; returns whether an existing ``what`` is being
    resumed. With ``force`` an existing folder's contents are deleted first, but only if it
    holds ``marker`` (a file every ``what`` has, e.g. ``config.json``): a folder that is not
    one of ours is never deleted."""
    path = Path(path)
    if resume and force:
        raise ValueError("give --resume (continue) or --force (replace), not both")
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path} exists and is not a folder; choose another output path")
    if not (path.exists() and any(path.iterdir())):
        if resume:
            raise FileNotFoundError(f"nothing to resume: {path} does not hold a {what}")
        path.mkdir(parents=True, exist_ok=True)
        return False
    if resume:
        return True
    if force:
        if marker is not None and not (path / marker).exists():
            raise OutputExistsError(
                f"{path} is not empty and holds no {marker}: not a {what}; refusing to delete "
                "it. Choose another output folder"
            )
        shutil.rmtree(path)
        path.mkdir(parents=True)
        return False
    raise OutputExistsError(
        f"{path} already holds a {what}; pass --resume to continue it or --force to replace it "
        "(or choose another output folder)"
    )


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
