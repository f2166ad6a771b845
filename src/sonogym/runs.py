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
import shutil
from pathlib import Path
from typing import Any


class OutputExistsError(FileExistsError):
    """An output folder already holds something; the message says how to continue or replace."""


def prepare_output(path: str | Path, resume: bool, force: bool, what: str = "run") -> bool:
    """Apply the output-folder rule to ``path``; returns whether an existing ``what`` is being
    resumed. With ``force`` an existing folder's contents are deleted first."""
    path = Path(path)
    if resume and force:
        raise ValueError("give --resume (continue) or --force (replace), not both")
    exists = path.exists() and (not path.is_dir() or any(path.iterdir()))
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path} exists and is not a folder; choose another output path")
    if not exists:
        if resume:
            raise FileNotFoundError(f"nothing to resume: {path} does not hold a {what}")
        path.mkdir(parents=True, exist_ok=True)
        return False
    if resume:
        return True
    if force:
        shutil.rmtree(path)
        path.mkdir(parents=True)
        return False
    raise OutputExistsError(
        f"{path} already holds a {what}; pass --resume to continue it or --force to replace it "
        "(or choose another output folder)"
    )


def _temporary(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp{os.getpid()}")


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    path = Path(path)
    tmp = _temporary(path)
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent))


def atomic_torch_save(obj: Any, path: str | Path) -> Path:
    """``torch.save`` through a temporary file and a rename."""
    import torch

    path = Path(path)
    tmp = _temporary(path)
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


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
