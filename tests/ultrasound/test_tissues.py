import math

import pytest
import torch

from sonogym.anatomy.labels import LABELS
from sonogym.ultrasound import (
    GEL,
    PHYSICAL_LABEL_TISSUE,
    PHYSICAL_TISSUES,
    REFERENCE_LABEL_TISSUE,
    REFERENCE_TISSUES,
    Tissue,
    TissueTable,
    physical_table,
    reference_table,
)

ALL_IDS = [0, *LABELS]


@pytest.mark.parametrize("mapping", [REFERENCE_LABEL_TISSUE, PHYSICAL_LABEL_TISSUE])
def test_every_label_id_is_mapped_explicitly(mapping):
    assert set(ALL_IDS) <= set(mapping)
    assert GEL in mapping


def test_sonogym_uses_the_intended_mapping_without_the_chain_bug():
    m = REFERENCE_LABEL_TISSUE
    assert m[5] == 11  # liver (the reference's chain sent it to "lung")
    assert m[2] == m[3] == 6  # kidneys
    assert m[1] == 12 and m[7] == 12  # spleen, pancreas
    assert all(m[i] == 2 for i in range(10, 15))  # lungs
    assert all(m[i] == 13 for i in range(25, 51))  # vertebrae
    assert m[79] == 10 and m[86] == 8 and m[52] == 15 and m[91] == 14 and m[90] == 9
    assert m[118] == m[119] == m[120] == m[121] == 12 and m[122] == 10
    assert m[123] == m[124] == 12  # ligaments, fascia: no ligament tissue in the reference
    assert m[0] == 0


def test_sonogym_constants_are_the_references():
    t = REFERENCE_TISSUES
    assert t[12] == Tissue(1.09, 1.63, 0.43, 0.41, 0.0)
    assert t[13] == Tissue(7.8, 90.0, 0.78, 0.56, 0.1)
    assert t[8] == Tissue(1.09, 0.4, 0.7, 0.65, 0.0)
    assert t[15] == Tissue(0.5, 1.06, 0.9, 0.65, 0.24)
    assert t[0].mu0 == 0.0 and t[0].alpha == 0.2


def _r(a: str, b: str) -> float:
    za, zb = PHYSICAL_TISSUES[a].impedance, PHYSICAL_TISSUES[b].impedance
    return (zb - za) / (zb + za)


def test_physical_reflection_coefficients_match_the_literature():
    # Literature: soft tissue/bone amplitude R 0.58-0.70, fat/muscle ~0.1,
    # tissue/air ~ -1
    assert 0.58 <= _r("muscle", "bone") * 1.09 <= 0.70  # bone at 1400 HU: CT ratio 2400/2200
    assert 0.5 <= _r("soft_tissue", "bone") <= 0.70
    assert 0.08 <= _r("fat", "muscle") <= 0.12
    assert _r("soft_tissue", "air") < -0.999
    assert PHYSICAL_TISSUES["bone"].alpha >= 5  # dB/cm/MHz: casts a shadow
    assert 0.5 <= PHYSICAL_TISSUES["soft_tissue"].alpha <= 0.7


def test_ligaments_and_fascia_image_as_echogenic_dense_tissue():
    phys = physical_table()
    assert phys.tissue_of(123) == phys.tissue_of(124) == "ligament"
    lig, muscle, fat = (PHYSICAL_TISSUES[k] for k in ("ligament", "muscle", "fat"))
    assert lig.mu0 > muscle.mu0 and lig.mu0 > fat.mu0  # brighter speckle than its neighbours
    assert _r("fat", "ligament") > _r("fat", "muscle") > 0  # a brighter interface under fat
    assert lig.alpha > muscle.alpha


def test_table_columns_are_label_indexed():
    tab = reference_table()
    col = tab.column("alpha")
    assert col.shape == (256,) and col.dtype == torch.float64
    assert col[28] == 7.8 and col[120] == 1.09 and col[GEL] == 0.2
    assert col[200] == 1.09  # unknown ids image as soft tissue
    phys = physical_table()
    assert phys.column("impedance")[119] == PHYSICAL_TISSUES["fat"].impedance
    assert phys.tissue_of(122) == "fluid"
    with pytest.raises(KeyError, match="unknown tissue field"):
        tab.column("density")


def test_table_rejects_missing_parameters():
    with pytest.raises(KeyError, match="no parameters"):
        TissueTable({1: "unobtainium"}, {"soft": Tissue(1, 1, 0, 0, 0)}, "soft")


def test_physical_scattering_is_fully_developed_in_parenchyma():
    for name in ("soft_tissue", "muscle", "liver", "fat"):
        t = PHYSICAL_TISSUES[name]
        assert 0.5 * (1 + math.erf(t.mu1 / math.sqrt(2))) > 0.95
    assert PHYSICAL_TISSUES["fluid"].mu0 < 0.1 and PHYSICAL_TISSUES["blood"].mu0 < 0.1
