"""On-disk cache entries of built patients (phantoms, real-derived variants).

An entry is ``<stem>.npz`` (the CT as int16 and the labels: plain arrays, nothing unpickled) and
a ``<stem>.json`` sidecar (name, affine, provenance and a SHA-256 over all of it), each written
to a temporary file and renamed, so readers never see a partial entry. ``cached_patient`` reads
an entry, or builds and writes it; an entry that does not verify is reported with a warning
naming it and rebuilt; temporary files left by killed writers are removed.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from sonogym.anatomy.patient import Patient
from sonogym.runs import atomic_write, atomic_write_json, remove_stale_temporaries


def _digest(arrays: dict[str, np.ndarray], info: dict) -> str:
    h = hashlib.sha256(json.dumps(info, sort_keys=True).encode())
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(f"{k}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.reshape(-1).view(np.uint8))  # the bytes in place, not a copy of them
    return h.hexdigest()


def write_entry(stem: Path, patient: Patient) -> None:
    """``patient`` as the entry ``stem`` (its CT must hold integer HU: it is stored as int16)."""
    arrays = {"ct": patient.ct.to(torch.int16).numpy(), "labels": patient.labels.numpy()}
    info = {
        "format": 1,
        "name": patient.name,
        "affine": patient.affine.tolist(),
        "meta": patient.meta,
    }
    info = json.loads(json.dumps(info, default=str))  # what the sidecar will hold, exactly
    side = {**info, "sha256": _digest(arrays, info)}
    atomic_write(stem.with_suffix(".npz"), lambda f: np.savez(f, **arrays))
    atomic_write_json(stem.with_suffix(".json"), side, indent=None)


def read_entry(stem: Path) -> Patient:
    """The patient of entry ``stem``; raises if it is missing, unreadable or does not verify."""
    side = json.loads(stem.with_suffix(".json").read_text())
    want = side.pop("sha256")
    with np.load(stem.with_suffix(".npz"), allow_pickle=False) as z:
        arrays = {k: z[k] for k in ("ct", "labels")}
    if _digest(arrays, side) != want:
        raise ValueError("checksum mismatch")
    return Patient(
        ct=torch.from_numpy(arrays["ct"].astype(np.float32)),
        labels=torch.from_numpy(arrays["labels"]),
        affine=np.asarray(side["affine"], dtype=np.float64),
        name=side["name"],
        meta=side["meta"],
    )


def cached_patient(stem: Path, build: Callable[[], Patient], what: str) -> Patient:
    """The entry ``stem`` (``what`` names it in warnings), or ``build()`` written there."""
    folder = stem.parent
    remove_stale_temporaries(folder)
    if stem.with_suffix(".json").exists() or stem.with_suffix(".npz").exists():
        try:
            return read_entry(stem)
        except Exception as e:  # any failure to verify: report, then rebuild
            warnings.warn(
                f"{what} cache entry {stem}.npz/.json is unreadable or corrupt ({e}); "
                "rebuilding it",
                RuntimeWarning,
                stacklevel=3,
            )
    patient = build()
    folder.mkdir(parents=True, exist_ok=True)
    write_entry(stem, patient)
    return patient
