"""The phantom cohort every evaluation protocol uses, in one place.

Patients are procedural phantom seeds (``sonogym.anatomy.load_phantom``):

* ``TRAIN_PATIENTS`` = seeds 0-4: the five training patients (paper: "train on 5 patients");
* ``HELD_OUT_PATIENTS`` = seed 5: the held-out sixth patient, never in a training config.

More held-out patients come from :func:`held_out` (seeds 5, 6, ... 99), which never overlap
the training seeds. ``POPULATION_PATIENTS`` = seeds 100-131: the 32 training phantoms of the
population study (policies trained across many patients, tested on held-out ones; CLI
``--patients 100-131``). Phantom seeds >= ``LEARNED_DATA_SEEDS`` (1000) are the learned
simulator's training phantoms (``sonogym lb-data``) and are not handed out as patients either.
``SELECTION_PATIENTS`` = seeds 900-904: phantoms for choosing a checkpoint (``sonogym
select``), apart from every training and held-out seed, so that no reported figure comes from
a patient the checkpoint was chosen on.
"""

from __future__ import annotations

from collections.abc import Iterable

#: Training patients (phantom seeds).
TRAIN_PATIENTS: tuple[int, ...] = (0, 1, 2, 3, 4)
#: The held-out patient(s) of the out-of-domain-patient test (phantom seeds).
HELD_OUT_PATIENTS: tuple[int, ...] = (5,)
#: First phantom seed of the learned simulator's paired data (kept apart from patients).
LEARNED_DATA_SEEDS = 1000
#: The population study's training phantoms (seeds 100-131), apart from every held-out seed.
POPULATION_PATIENTS: tuple[int, ...] = tuple(range(100, 132))
#: Phantoms for checkpoint selection (seeds 900-904): never trained on, never reported.
SELECTION_PATIENTS: tuple[int, ...] = tuple(range(900, 905))


def held_out(n: int = 1) -> tuple[int, ...]:
    """``n`` held-out phantom seeds: 5, 6, ... 99 (never a training seed of the cohort or
    the population, never the learned simulator's data)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    first = max(TRAIN_PATIENTS) + 1
    seeds = tuple(range(first, first + n))
    if seeds[-1] >= POPULATION_PATIENTS[0]:
        raise ValueError(
            f"at most {POPULATION_PATIENTS[0] - first} held-out phantoms (seeds "
            f"{POPULATION_PATIENTS[0]}-{POPULATION_PATIENTS[-1]} are the population's training "
            f"phantoms, seeds >= {LEARNED_DATA_SEEDS} the learned simulator's data)"
        )
    assert not set(seeds) & set(TRAIN_PATIENTS)
    return seeds


def patient_key(p: int | str) -> int | str:
    """A comparable key of a patient spec: an int seed, or a folder path as given (a digit
    string, as the CLI passes it, is the seed it names)."""
    if isinstance(p, bool):
        raise TypeError(f"patient {p!r}: use an int phantom seed or a folder path")
    if isinstance(p, int):
        return p
    s = str(p)
    return int(s) if s.lstrip("-").isdigit() else s


def overlap(a: Iterable[int | str], b: Iterable[int | str]) -> tuple[int | str, ...]:
    """The patients that ``a`` and ``b`` share (sorted by their string form)."""
    common = {patient_key(p) for p in a} & {patient_key(p) for p in b}
    return tuple(sorted(common, key=str))
