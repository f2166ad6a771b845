"""Real-derived patients: variants of the shared real subject, by seed (built at 2 mm to keep
the tests fast; the grid at 1 mm is checked against the memory bound)."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from sonogym.anatomy import labels as L
from sonogym.anatomy import variants as V
from sonogym.anatomy.variants import VariantParams, load_variant, make_variant, variant_grid
from sonogym.cli import parse_patients
from sonogym.envs.patients import resolve_patients
from sonogym.envs.registry import make_vec

SUBJECT = str(Path(__file__).resolve().parents[1] / "data" / "totalsegmentator_example")
FAST = VariantParams(spacing=0.002)
LEVELS = ("L1", "L2", "L3", "L4", "L5")
#: Every parameter neutral, no random displacement: one parameter at a time is measured.
NEUTRAL = dict(
    spacing=0.002,
    lordosis_change=0.0,
    soft_tissue_scale=1.0,
    segment_scale=(1.0,) * 5,
    size_scale=(1.0,) * 5,
    jitter=0.0,
)


@pytest.fixture(scope="module")
def source():
    return V._source(str(Path(SUBJECT).resolve()), 0.002)


def _lordosis_deg(p) -> float:
    """Sagittal angle (deg) between L5's and L1's superior axes."""
    f1, f5 = p.landmarks.vertebra("L1"), p.landmarks.vertebra("L5")
    return math.degrees(
        math.atan2(f5.superior[1], f5.superior[2]) - math.atan2(f1.superior[1], f1.superior[2])
    )


def _skin_to_tip(p, level="L4") -> float:
    """Depth (m) from the back's skin to the spinous tip of ``level``, over its body."""
    f = p.landmarks.vertebra(level)
    idx = np.argwhere(p.labels.numpy() == L.VERTEBRA_IDS[level])
    tip = p.origin[1] + idx[:, 1].min() * p.spacing[1]
    return tip - p.skin.height(torch.tensor(f.centre[0]), torch.tensor(f.centre[2])).item()


def _span(p) -> float:
    lm = p.landmarks
    return float(np.linalg.norm(lm.vertebra("L1").centre - lm.vertebra("L5").centre))


def test_same_seed_gives_the_same_variant_bit_for_bit():
    a = make_variant(SUBJECT, 3, FAST)
    V._source.cache_clear()  # the subject read again from its files
    b = make_variant(SUBJECT, 3, FAST)
    assert torch.equal(a.ct, b.ct) and torch.equal(a.labels, b.labels)
    assert np.array_equal(a.affine, b.affine) and a.meta == b.meta
    assert torch.equal(a.ct, torch.round(a.ct))  # integer HU, as the cache stores them


def test_variants_differ_and_plan_their_landmarks(source):
    variants = [make_variant(SUBJECT, i, FAST) for i in (0, 1, 2)]
    l4 = [v.landmarks.vertebra("L4").centre for v in variants]
    depth = [_skin_to_tip(v) for v in variants]
    for i, v in enumerate(variants):
        assert v.name == f"totalsegmentator_example@{i}"
        p = v.meta["params"]
        lo, hi = V.VARIANT_RANGES["soft_tissue_scale"]
        assert lo <= p["soft_tissue_scale"] <= hi and len(p["segment_scale"]) == 5
        for lv in LEVELS:  # every level keeps a frame and both corridors
            v.landmarks.vertebra(lv)
            for side in ("left", "right"):
                assert v.landmarks.trajectory(lv, side).radius >= 0.0015
        # the skin-to-tip depth follows the drawn scale (within the random displacement)
        assert depth[i] == pytest.approx(_skin_to_tip(source) * p["soft_tissue_scale"], abs=4e-3)
        for j in range(i):
            assert np.linalg.norm(l4[i] - l4[j]) > 5e-4  # L4 moved between variants
            assert abs(depth[i] - depth[j]) > 1e-3
            assert v.meta["speckle_seed"] != variants[j].meta["speckle_seed"]
    assert len({v.meta["speckle_seed"] for v in variants} | {source.meta["speckle_seed"]}) == 4


@pytest.fixture(scope="module")
def neutral():
    """The subject on a variant's grid, undeformed."""
    return make_variant(SUBJECT, 0, VariantParams(**NEUTRAL))


def test_neutral_variant_is_the_source_cropped(source, neutral):
    for lv in LEVELS:
        a, b = neutral.landmarks.vertebra(lv), source.landmarks.vertebra(lv)
        assert np.linalg.norm(a.centre - b.centre) < 1e-3
    assert _skin_to_tip(neutral) == pytest.approx(_skin_to_tip(source), abs=1e-3)


@pytest.mark.parametrize("change", [0.12, -0.12])
def test_lordosis_change_turns_l1_against_l5(neutral, change):
    v = make_variant(SUBJECT, 0, VariantParams(**{**NEUTRAL, "lordosis_change": change}))
    assert _lordosis_deg(v) - _lordosis_deg(neutral) == pytest.approx(math.degrees(change), abs=1.5)


def test_soft_tissue_scale_scales_the_depth_behind_the_spine(source):
    v = make_variant(SUBJECT, 0, VariantParams(**{**NEUTRAL, "soft_tissue_scale": 1.3}))
    for lv in ("L2", "L4"):
        assert _skin_to_tip(v, lv) == pytest.approx(1.3 * _skin_to_tip(source, lv), abs=2.5e-3)
    # the bone itself is where it was
    assert (
        np.linalg.norm(v.landmarks.vertebra("L4").centre - source.landmarks.vertebra("L4").centre)
        < 1e-3
    )


def test_segment_and_size_scales_stretch_and_widen_the_levels(source):
    longer = make_variant(SUBJECT, 0, VariantParams(**{**NEUTRAL, "segment_scale": (1.07,) * 5}))
    assert _span(longer) / _span(source) == pytest.approx(1.07, abs=0.01)
    wider = make_variant(SUBJECT, 0, VariantParams(**{**NEUTRAL, "size_scale": (1.07,) * 5}))
    vid = L.VERTEBRA_IDS["L3"]
    ratio = (wider.labels == vid).sum().item() / (source.labels == vid).sum().item()
    assert ratio == pytest.approx(1.07**2, abs=0.06)  # axial area, same height
    assert _span(wider) == pytest.approx(_span(source), abs=1.5e-3)


def test_variant_grid_at_1mm_fits_the_memory_bound(source):
    origin, shape = variant_grid(source, 0.001)
    assert math.prod(shape) * 5 <= V.MAX_VARIANT_BYTES  # float32 CT + uint8 labels
    # it still holds L1-L5 whole, with their margins, and the back
    lum = np.argwhere(np.isin(source.labels.numpy(), list(L.LUMBAR_VERTEBRAE.values())))
    pts = source.origin + lum * source.spacing
    hi = origin + (np.array(shape) - 1) * 0.001
    assert (pts[:, 2] >= origin[2] + 0.02).all() and (pts[:, 2] <= hi[2] - 0.02).all()
    # +-130 mm to the sides: a navigation probe (face within +-90 mm of L4, images 37.5 mm to
    # either side of it) never images past the volume
    assert shape[0] * 0.001 >= 0.255


def test_cache_round_trip_and_key(tmp_path):
    a = load_variant(SUBJECT, 1, FAST, cache=tmp_path)
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".json", ".npz"]
    b = load_variant(SUBJECT, 1, FAST, cache=tmp_path)
    assert torch.equal(a.ct, b.ct) and torch.equal(a.labels, b.labels) and a.meta == b.meta
    assert V.variant_cache_key(SUBJECT, 1, FAST) != V.variant_cache_key(SUBJECT, 2, FAST)
    npz = next(tmp_path.glob("*.npz"))
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.warns(RuntimeWarning, match=f"variant cache entry .*{npz.stem}.*corrupt"):
        c = load_variant(SUBJECT, 1, FAST, cache=tmp_path)
    assert torch.equal(a.ct, c.ct)


def test_patients_spec_names_variants():
    assert parse_patients(["0-2", f"{SUBJECT}@4-6", f"{SUBJECT}@9", "7"]) == (
        0, 1, 2, f"{SUBJECT}@4", f"{SUBJECT}@5", f"{SUBJECT}@6", f"{SUBJECT}@9", 7,
    )  # fmt: skip
    assert parse_patients([SUBJECT]) == (SUBJECT,)
    assert V.parse_variant(f"{SUBJECT}@12") == (SUBJECT, 12)
    assert V.parse_variant(SUBJECT) is None and V.parse_variant("nowhere@3") is None


def test_env_runs_on_variants():
    specs = (f"{SUBJECT}@0", f"{SUBJECT}@1")
    patients = resolve_patients(specs, 0.002)
    assert [p.name for p in patients] == [
        "totalsegmentator_example@0",
        "totalsegmentator_example@1",
    ]
    env = make_vec("navigation", 2, patients=specs, phantom_spacing=0.002, obs_mode="state")
    obs, _ = env.reset(seed=0)
    obs, reward, term, trunc, _ = env.step(torch.zeros(env.action_space.shape))
    assert torch.isfinite(torch.as_tensor(reward)).all()
    centres = env.unwrapped.scene.target_centres_p.cpu().numpy()
    assert np.allclose(centres[0], patients[0].landmarks.vertebra("L4").centre)
    assert not np.allclose(centres[0], centres[1])
    env.close()
