"""Turn an env's ``patients`` option (phantom seeds and/or TotalSegmentator folders) into
Patients, shared between envs of one process."""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

from sonogym.anatomy import (
    LandmarkError,
    Patient,
    PatientError,
    PhantomParams,
    load_phantom,
    load_totalsegmentator,
)

PatientSpec = int | str | Path

#: The vertebra every task is built around.
TARGET = "L4"


#: Patients kept loaded in-process (full volumes: ~120 MB each at 1 mm), for envs built one
#: after another on the same patients (evaluation, tests); built envs keep only what they need.
CACHED_PATIENTS = 4


@lru_cache(maxsize=CACHED_PATIENTS)
def _load(spec: int | str, spacing: float) -> Patient:
    if isinstance(spec, int):
        return load_phantom(spec, PhantomParams(spacing=spacing))
    try:
        patient = load_totalsegmentator(spec, spacing=spacing, target=TARGET)
        patient.landmarks.vertebra(TARGET)  # every task needs its frame: fail here, not later
    except (PatientError, LandmarkError, FileNotFoundError) as e:
        if spec in str(e):
            raise
        raise type(e)(f"patient folder {spec}: {e}") from e
    return patient


def resolve_patients(specs: Sequence[PatientSpec] | PatientSpec, spacing: float) -> list[Patient]:
    """Patients for a list of phantom seeds (int) and/or folders (str or Path).

    Phantoms come from the on-disk cache (built once); loaded patients are shared in-process.
    A folder is loaded with its L4 required whole (``load_totalsegmentator(target="L4")``) and
    its L4 frame computed; any problem raises an error naming the folder.
    """
    if isinstance(specs, int | str | Path):
        specs = [specs]
    if len(specs) == 0:
        raise ValueError("patients must name at least one phantom seed or patient folder")
    out = []
    for s in specs:
        if isinstance(s, bool) or not isinstance(s, int | str | Path):
            raise TypeError(
                f"patient {s!r}: use an int phantom seed or a TotalSegmentator folder path"
            )
        out.append(_load(s if isinstance(s, int) else _folder(s), float(spacing)))
    return out


def _folder(spec: str | Path) -> str:
    """A patient folder's absolute path (the cache key); a symlink loop is named, not a
    traceback (``Path.resolve`` raises ``RuntimeError`` for one before Python 3.13)."""
    try:
        return str(Path(spec).resolve())
    except (RuntimeError, OSError) as e:
        raise PatientError(
            f"patient folder {spec}: its path cannot be resolved ({e}); a symlink in it points "
            "back to itself: give the subject folder itself, or fix the link"
        ) from None
