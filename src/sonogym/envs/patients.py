"""Turn an env's ``patients`` option (phantom seeds, TotalSegmentator folders and/or variants of
them, ``"DIR@7"``) into Patients, shared between envs of one process."""

from __future__ import annotations

import contextlib
import contextvars
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from sonogym.anatomy import (
    LandmarkError,
    Patient,
    PatientError,
    PatientModel,
    PhantomParams,
    load_phantom,
    load_totalsegmentator,
)
from sonogym.anatomy.variants import VariantParams, load_variant, parse_variant

PatientSpec = int | str | Path

#: The vertebra every task is built around.
TARGET = "L4"


#: Patient models (grid, skin, landmarks: ~1.5 MB each) kept in-process, so an env built again
#: on the same patients (evaluation, tests) reloads only the volumes from the on-disk cache
#: (0.5 s at 1 mm) and does not re-plan the landmarks (2 s).
CACHED_MODELS = 64

#: Patients with their full volumes (~120 MB each at 1 mm), shared while anything holds them
#: (envs built side by side on the same patients) and freed with their last user: a built env
#: keeps only what it needs, so nothing here outlives it.
_live: weakref.WeakValueDictionary[tuple[int | str, float], Patient] = weakref.WeakValueDictionary()
_models: OrderedDict[tuple[int | str, float], PatientModel] = OrderedDict()


#: Who is told of each patient an env build loads (``patient_progress``); nobody by default.
_on_loaded: contextvars.ContextVar[Callable[[int | str], None] | None] = contextvars.ContextVar(
    "sonogym_patient_progress", default=None
)


@contextlib.contextmanager
def patient_progress(callback: Callable[[int | str], None]) -> Iterator[None]:
    """Within the block, ``callback(spec)`` is called after each patient is loaded (built,
    read from the cache or shared), e.g. to show a command's progress through an env's
    patients; the simulator itself prints nothing."""
    token = _on_loaded.set(callback)
    try:
        yield
    finally:
        _on_loaded.reset(token)


def _load(spec: int | str, spacing: float) -> Patient:
    patient = _load_or_share(spec, spacing)
    callback = _on_loaded.get()
    if callback is not None:
        callback(spec)
    return patient


def _load_or_share(spec: int | str, spacing: float) -> Patient:
    key = (spec, spacing)
    patient = _live.get(key)
    if patient is not None:
        return patient
    if isinstance(spec, int):
        patient = load_phantom(spec, PhantomParams(spacing=spacing))
    else:
        variant = parse_variant(spec)
        try:
            if variant is not None:
                patient = load_variant(*variant, VariantParams(spacing=spacing))
            else:
                patient = load_totalsegmentator(spec, spacing=spacing, target=TARGET)
        except (PatientError, FileNotFoundError) as e:
            if spec in str(e):
                raise
            raise type(e)(f"patient folder {spec}: {e}") from e
    model = _models.get(key)
    if model is not None and model.meta == patient.meta and model.shape == patient.shape:
        patient.adopt(model)  # the same volumes as before: their skin and landmarks too
        _models.move_to_end(key)
    else:
        try:  # every task needs the target's frame: fail here, naming the folder, not later
            patient.landmarks.vertebra(TARGET)
        except LandmarkError as e:
            if isinstance(spec, int) or spec in str(e):
                raise
            raise LandmarkError(f"patient folder {spec}: {e}") from e
        _models[key] = patient.model()
        if len(_models) > CACHED_MODELS:
            _models.popitem(last=False)
    _live[key] = patient
    return patient


def resolve_patients(specs: Sequence[PatientSpec] | PatientSpec, spacing: float) -> list[Patient]:
    """Patients for a list of phantom seeds (int), folders (str or Path) and variants of folders
    (``"DIR@7"``: variant 7 of the subject in DIR, ``sonogym.anatomy.variants``).

    Phantoms and variants come from the on-disk cache (built once); a patient's volumes are
    shared in-process while anything holds them, its skin and landmarks are kept
    (``CACHED_MODELS``). A folder is loaded with its L4 required whole
    (``load_totalsegmentator(target="L4")``) and its L4 frame computed; any problem raises an
    error naming the folder.
    """
    if isinstance(specs, int | str | Path):
        specs = [specs]
    if len(specs) == 0:
        raise ValueError("patients must name at least one phantom seed or patient folder")
    out = []
    for s in specs:
        if isinstance(s, bool) or not isinstance(s, int | str | Path):
            raise TypeError(
                f"patient {s!r}: use an int phantom seed, a TotalSegmentator folder path or "
                "'FOLDER@N' (variant N of that subject)"
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
