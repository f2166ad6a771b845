"""The benchmark's patients and learned nets are frozen: a change to what the phantom generator
makes for a cohort seed, or to a shipped net's weights, fails here unless it comes with a new
version (``GENERATOR_VERSION``; a net's new digest in the model card).

The fingerprint (``tests/data/cohort_fingerprint.json``) holds, for every seed of the benchmark
cohort (training phantoms 0-4, held-out 5-9, the population 100-163, the selection phantoms
900-904), a digest of what the generator draws from the seed (``PhantomParams.resolved`` and
the per-level variation), and for three phantoms built at the tests' 2 mm the voxel count of
every label; the slow test builds every cohort phantom. After a deliberate change (version
bumped), write a new fingerprint: ``python tests/anatomy/test_cohort_fingerprint.py`` (all
seeds at 2 mm: ~8 CPU min).
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from sonogym.anatomy import PhantomParams, make_phantom
from sonogym.anatomy.phantom import GENERATOR_VERSION, _level_variation
from sonogym.evaluation.cohort import HELD_OUT_PATIENTS, SELECTION_PATIENTS, TRAIN_PATIENTS
from sonogym.ultrasound.learned.shipped import NUM_SHIPPED, net_digests

FINGERPRINT = Path(__file__).resolve().parents[1] / "data" / "cohort_fingerprint.json"
DOCS_CARD = Path(__file__).resolve().parents[2] / "docs" / "learned_model_card.json"
SPACING = 0.002  # m, the tests' phantoms
#: every cohort seed: training, held-out (5 and the 5-9 of the population evaluation), the
#: population the shipped navigation policy trains on and the checkpoint-selection phantoms
COHORT = sorted(
    {*TRAIN_PATIENTS, *HELD_OUT_PATIENTS, *range(5, 10), *range(100, 164), *SELECTION_PATIENTS}
)
#: built in the default test run (one training, one held-out, one population phantom)
BUILT = (0, 5, 100)
#: label voxels that may differ between CPUs (float rounding on a surface), per label: a
#: generator change moves far more
VOXEL_SLACK = 3


def _draws(seed: int) -> str:
    """Digest of everything the generator draws from ``seed``."""
    p = PhantomParams(spacing=SPACING).resolved(seed)
    fields = json.dumps({k: round(v, 12) if isinstance(v, float) else v
                         for k, v in sorted(vars(p).items())}, default=str)  # fmt: skip
    levels = np.round(_level_variation(seed, p), 12).tobytes()
    return hashlib.sha256(fields.encode() + levels).hexdigest()[:16]


def _voxels(seed: int) -> dict[str, int]:
    labels = make_phantom(seed, PhantomParams(spacing=SPACING)).labels.numpy()
    counts = np.bincount(labels.ravel())
    return {str(k): int(n) for k, n in enumerate(counts) if n}


def _recorded() -> dict:
    rec = json.loads(FINGERPRINT.read_text())
    if rec["generator_version"] != GENERATOR_VERSION:
        pytest.fail(
            f"the phantom generator is version {GENERATOR_VERSION}, the cohort fingerprint is of "
            f"version {rec['generator_version']}: write the new one (python {__file__})"
        )
    return rec


def test_every_cohort_seed_draws_what_it_drew():
    rec = _recorded()
    assert sorted(map(int, rec["draws"])) == COHORT
    changed = [s for s in COHORT if _draws(s) != rec["draws"][str(s)]]
    assert not changed, (
        f"phantom seeds {changed} draw other parameters under generator version "
        f"{GENERATOR_VERSION}: bump GENERATOR_VERSION for a deliberate change"
    )


def _check_voxels(seeds) -> None:
    rec = _recorded()
    for seed in seeds:
        got, want = _voxels(seed), rec["voxels"][str(seed)]
        assert set(got) == set(want), f"phantom {seed}: labels {sorted(got)} vs {sorted(want)}"
        off = {k: got[k] - want[k] for k in want if abs(got[k] - want[k]) > VOXEL_SLACK}
        assert not off, (
            f"phantom {seed} at {SPACING * 1e3:.0f} mm: label voxel counts moved {off} under "
            f"generator version {GENERATOR_VERSION}: bump GENERATOR_VERSION for a deliberate "
            "change"
        )


def test_cohort_phantoms_are_what_they_were():
    _check_voxels(BUILT)


@pytest.mark.slow
def test_every_cohort_phantom_is_what_it_was():
    _check_voxels(COHORT)


def test_shipped_learned_nets_are_the_model_cards():
    card = json.loads(DOCS_CARD.read_text())
    digests = net_digests(tuple(range(NUM_SHIPPED)))
    assert digests == card["digests"], (
        "a shipped learned net's weights differ from those the model card describes: "
        "regenerate the card (docs/learned_model_card.json) with the new nets' figures"
    )


def write_fingerprint() -> None:
    rec = {
        "generator_version": GENERATOR_VERSION,
        "spacing_m": SPACING,
        "draws": {str(s): _draws(s) for s in COHORT},
        "voxels": {str(s): _voxels(s) for s in COHORT},
    }
    FINGERPRINT.write_text(json.dumps(rec, indent=1, sort_keys=True) + "\n")
    print(f"wrote {FINGERPRINT} ({len(COHORT)} phantoms, generator version {GENERATOR_VERSION})")


if __name__ == "__main__":
    sys.exit(write_fingerprint())
