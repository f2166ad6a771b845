import pytest

from sonogym.anatomy import labels as L


def test_totalsegmentator_v2_ids_of_spine_structures():
    # TotalSegmentator v2 "total" ids (never the v1 ids, which differ).
    expected = {
        "vertebrae_L4": 28,
        "vertebrae_L1": 31,
        "vertebrae_L5": 27,
        "vertebrae_T12": 32,
        "vertebrae_S1": 26,
        "sacrum": 25,
        "spinal_cord": 79,
        "autochthon_left": 86,
        "autochthon_right": 87,
        "iliopsoas_left": 88,
        "iliopsoas_right": 89,
        "kidney_right": 2,
        "kidney_left": 3,
        "liver": 5,
        "aorta": 52,
        "inferior_vena_cava": 63,
        "hip_left": 77,
        "hip_right": 78,
        "rib_left_12": 103,
        "rib_right_12": 115,
        "costal_cartilages": 117,
    }
    for name, i in expected.items():
        assert L.LABEL_IDS[name] == i, name
    assert len(L.TOTALSEG_V2) == 117 and set(L.TOTALSEG_V2) == set(range(1, 118))


def test_project_ids_start_at_118_and_body_is_120():
    assert L.BODY_TRUNC == 120
    assert min(L.PROJECT_LABELS) == 118
    assert set(L.PROJECT_LABELS.values()) >= {
        "skin",
        "subcutaneous_fat",
        "body_trunc",
        "intervertebral_discs",
        "spinal_canal",
    }
    # what the phantom draws and TotalSegmentator has no class for
    assert L.LABEL_IDS["spinal_ligaments"] == L.SPINAL_LIGAMENTS == 123
    assert L.LABEL_IDS["thoracolumbar_fascia"] == L.THORACOLUMBAR_FASCIA == 124
    assert L.label_id("spinal_ligaments") == 123


def test_label_id_accepts_names_levels_ids_and_rejects_unknown():
    assert L.label_id("L4") == 28
    assert L.label_id("vertebrae_L4") == 28
    assert L.label_id(120) == 120
    with pytest.raises(KeyError, match="vertebrae_L4"):
        L.label_id("vertebra_L4")
    with pytest.raises(KeyError):
        L.label_id(200)
