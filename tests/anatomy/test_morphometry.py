"""Morphometry measures what its docstring says (on shapes with known answers), and the shipped
real subject lies inside the phantom population's 5-95 % range on every value."""

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from sonogym.anatomy import Patient, PhantomParams, load_totalsegmentator, make_phantom
from sonogym.anatomy import labels as L
from sonogym.anatomy import phantom_spine as S
from sonogym.anatomy.morphometry import (
    LEVEL_MEASURES,
    LEVELS,
    PROFILE_OFFSETS,
    bone_hit_depths,
    first_bone_labels,
    measure,
    muscle_profile,
    skin_distance,
)
from sonogym.anatomy.phantom import GENERATOR_VERSION, _level_variation
from sonogym.viz.morphometry import outside, population_bounds

ROOT = Path(__file__).resolve().parents[2]
POPULATION = ROOT / "docs" / "results" / "morphometry" / "population.json"
SUBJECT = ROOT / "tests" / "data" / "totalsegmentator_example"


def _slab_patient():
    """1 mm box: air above y = 0, soft tissue below, a bone plate 30-35 mm deep with a 10 mm
    gap at |x| < 5 mm."""
    n = (81, 80, 81)
    ax = [np.arange(k) * 0.001 - 0.04 for k in n]
    x, y, _ = np.meshgrid(*ax, indexing="ij")
    labels = np.where(y >= 0, L.BODY_TRUNC, 0).astype(np.uint8)
    bone = (y >= 0.030) & (y <= 0.035) & (np.abs(x) >= 0.005)
    labels[bone] = L.VERTEBRA_IDS["L4"]
    ct = np.select([labels == 0, bone], [-1000.0, 1200.0], 20.0).astype(np.float32)
    affine = np.diag([0.001, 0.001, 0.001, 1.0])
    affine[:3, 3] = -0.04
    return Patient(ct=torch.from_numpy(ct), labels=torch.from_numpy(labels), affine=affine)


def test_bone_hit_depths_and_skin_distance_on_a_known_slab():
    p = _slab_patient()
    u = [-20.0, -8.0, 0.0, 4.0, 8.0, 20.0]
    d = bone_hit_depths(p, 0.0, 0.0, math.pi, u)  # transverse: u runs along -x
    skin = p.skin.height(torch.tensor(0.0), torch.tensor(0.0)).item()
    # the skin sits at the air/tissue edge (half a voxel above y = 0); the plate at 30 mm
    assert abs(skin + 0.0005) <= 0.0005
    for ui, di in zip(u, d, strict=True):
        if abs(ui) < 5:
            assert di == 100.0  # through the gap: no bone in the image
        else:
            assert abs(di - (30.0 - skin * 1e3)) <= 0.5, (ui, di)
    # the bone each beam meets first: the L4 plate, nothing through the gap
    first = first_bone_labels(p, 0.0, 0.0, math.pi, u)
    assert first.tolist() == [0 if abs(ui) < 5 else L.VERTEBRA_IDS["L4"] for ui in u]
    pts = np.array([[0.0, 0.02, 0.0], [0.01, 0.031, 0.0]])
    assert np.allclose(skin_distance(p, pts), (pts[:, 1] - skin) * 1e3, atol=0.3)


@pytest.fixture(scope="module")
def truth(small_phantom):
    """The generator's own vertebrae for the seed-0 2 mm phantom."""
    p = PhantomParams(spacing=0.002).resolved(0)
    return {
        v.level: v
        for v in S.place_spine(
            p.vertebra_scale, p.posterior_scale, p.disc_scale, p.lordosis, p.lordosis_apex,
            p.scoliosis * 1e3, p.axial_rotation, p.spine_rotation + p.trunk_roll,
            _level_variation(0, p),
        )
    }  # fmt: skip


def test_level_measures_match_the_generators_geometry(small_phantom, truth):
    m = measure(small_phantom)
    h = 2.0  # mm, voxel size
    for lv in LEVELS:
        v, row = truth[lv], m.levels[lv]
        d = v.dims
        # the spinous tip: the posterior-most point of the tip's rounded end
        tip = v.to_world(v.spinous_tip) * 1e-3
        assert abs(row["tip_depth"] - skin_distance(small_phantom, tip[None])[0]) <= 1.5 * h
        # transverse processes: their tips at +-tp_half_span, a little posterior (-> l-extent)
        assert abs(row["tp_span"] - 2 * d.tp_half_span) <= 1.5 * h, lv
        # body at mid-height: the waist makes it 5 % narrower than the endplates; the depth at
        # the midline runs from the canal's front (the posterior wall's 1 mm notch) to the front
        assert abs(row["body_width"] - 2 * d.body_half_width * 0.95) <= 1.5 * h, lv
        assert abs(row["body_depth"] - (2 * d.body_half_depth - 1.0)) <= 1.5 * h, lv
        # the facet joints lie at +-facet_half_distance of the joint below
        assert abs(row["facet_width"] - 2 * d.facet_half_distance) <= 4.0 + h, lv


def test_the_population_table_is_the_generators():
    pop = json.loads(POPULATION.read_text())
    assert pop["generator_version"] == GENERATOR_VERSION, (
        "the generator changed: regenerate the table with "
        "`sonogym morphometry --out docs/results/morphometry --doc docs/anatomy.md`"
    )
    assert len(pop["rows"]) >= 20
    spacing = pop["spacing_m"]
    for seed in ("0", "1"):
        got = measure(make_phantom(int(seed), PhantomParams(spacing=spacing))).flat()
        want = pop["rows"][seed]
        assert set(got) == set(want)
        for k, v in want.items():
            assert got[k] == pytest.approx(v, abs=1e-6, nan_ok=True), (seed, k)


def test_the_real_subject_lies_inside_the_phantom_population():
    pop = json.loads(POPULATION.read_text())
    real = load_totalsegmentator(SUBJECT, spacing=pop["subject_spacing_m"], target="L4")
    values = measure(real).flat()
    expected = [f"{lv} {m}" for lv in LEVELS for m in LEVEL_MEASURES]
    expected += [
        f"{v} {u:+.0f}" for v in ("transverse", "sagittal", "muscle") for u in PROFILE_OFFSETS
    ]
    assert sorted(values) == sorted(expected)
    assert values == pytest.approx(pop["subject_values"], abs=1e-6)  # the table's real column
    bounds = population_bounds(pop["rows"])
    assert outside(values, bounds) == [], {
        k: (values[k], bounds[k]) for k in outside(values, bounds)
    }


def test_muscle_profile_stops_at_bone_on_a_known_slab():
    """Muscle 15-28 mm deep beside a bone plate (30-35 mm, gap at |x| < 5 mm), more muscle below
    the plate: a beam reads the muscle above the plate, bone first beside the gap, and the deep
    muscle only through the gap."""
    p = _slab_patient()
    lab = p.labels.numpy().copy()
    ax = [np.arange(k) * 0.001 - 0.04 for k in lab.shape]
    x, y, _ = np.meshgrid(*ax, indexing="ij")
    lab[(y >= 0.015) & (y < 0.028) & (np.abs(x) >= 0.008)] = 86
    lab[y >= 0.037] = 87
    p = Patient(ct=p.ct, labels=torch.from_numpy(lab), affine=p.affine)
    skin = p.skin.height(torch.tensor(0.0), torch.tensor(0.0)).item() * 1e3
    frame = SimpleNamespace(centre=np.zeros(3))
    u = [-20.0, -6.5, 0.0, 6.5, 20.0]
    d = muscle_profile(p, frame, u)
    assert abs(d[0] - (15.0 - skin)) <= 0.5 and abs(d[4] - (15.0 - skin)) <= 0.5
    assert d[1] == d[3] == 100.0  # bone before any muscle
    assert abs(d[2] - (37.0 - skin)) <= 0.5  # through the gap, the muscle under the plate
