"""Label -> tissue tables and the two ultrasound models' acoustic parameters, as documented data.

Every label id the patient model uses (``sonogym.anatomy.labels``: background 0, TotalSegmentator
v2 ids 1-117, project ids 118-124) maps to one tissue in each model; ``GEL`` (255) is a pseudo
label the simulator gives to air in the first millimetres under the probe face (coupling gel).
Ids the tables do not list (125-254) image as generic soft tissue.

``reference`` model (the authors' reference code): the reference's ImFusion-style tissue
ids with its parameters copied exactly, and the *intended* TotalSegmentator -> tissue mapping of
its ``label_conversion.yaml`` (liver -> 11, kidneys -> 6, ...), not the chained in-place
relabelling that sent liver and kidneys to "lung". Its attenuation ``alpha`` is in the
reference's units: energy decays as exp(-0.02 * sum(alpha - beta) * dz / mm) (0.01 per 0.5 mm
pixel). Project ids: skin, subcutaneous fat and body_trunc -> 12 (soft tissue, as the reference's
body label 120); intervertebral discs -> 12 (the reference has no disc label: discs sit inside
its body label); spinal canal -> 10 (the reference's spinal-cord tissue, which is what
TotalSegmentator's spinal_cord mask covers in the lumbar canal); spinal ligaments and the
thoracolumbar fascia -> 12 (the reference has no ligament tissue; their echo comes from their CT
contrast with fat and muscle, which the model's CT-based reflection sees).

``physical`` model (literature values, sources below): literature impedance (MRayl) and attenuation
(dB/cm/MHz); scattering mu0 / mu1 / sigma0 with the paper's meaning (scatterer amplitude
mu0 + sigma0 * N0 where N1 <= mu1), chosen so that parenchyma gives fully developed speckle
(mu1 = 2: 98 % of pixels scatter) and fluids are near-anechoic; ``hu`` is the tissue's nominal
CT value. The impedance is refined by the CT through ``HU_IMPEDANCE``, a monotone CT -> impedance
curve through the same literature values: a pixel's impedance is Z_tissue * m(HU) / m(hu).
Sources: [B] Burger et al. 2013 table, [S] Sensors 2023, [D] Diagnostics 2023, [I] ImFusion,
[R] recalled / chosen here.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

#: Pseudo label of coupling gel (air right under the probe face); never in a patient's labels.
GEL = 255


@dataclass(frozen=True)
class Tissue:
    """Acoustic parameters of one tissue.

    Attributes:
        alpha: attenuation; ``physical``: dB/cm/MHz (one way, amplitude); ``reference``: the
            reference's units (decay exp(-0.02 * alpha * dz / mm)).
        impedance: acoustic impedance, MRayl (unused by the ``reference`` model, whose impedance
            comes from the CT; kept as the reference's data).
        mu0: mean scatterer amplitude.
        mu1: scatterer density threshold on a standard normal N1 (density = Phi(mu1)).
        sigma0: scatterer amplitude standard deviation.
        hu: nominal CT value, Hounsfield units (``physical`` impedance refinement).
    """

    alpha: float
    impedance: float
    mu0: float
    mu1: float
    sigma0: float
    hu: float = 0.0


# ---------------------------------------------------------------------------- reference
#: The authors' reference code's tissue table (ImFusion-style ids).
#: All tissues also share the large-scale amplitude A_l = 0.08 and cell f_l = 30 px (15 mm).
REFERENCE_TISSUES: dict[int, Tissue] = {
    0: Tissue(0.2, 0.04, 0.0, 0.0, 0.0),  # background / outside the body
    2: Tissue(0.2, 0.4, 0.7, 0.65, 0.0),  # lung
    3: Tissue(0.48, 1.42, 0.5, 0.5, 0.0),  # fat (unused by the mapping)
    4: Tissue(0.2, 1.5, 0.0, 0.0, 0.0),  # water (we use it for coupling gel)
    6: Tissue(0.2, 1.06, 0.49, 0.2, 0.0),  # kidney
    8: Tissue(1.09, 0.4, 0.7, 0.65, 0.0),  # muscle
    9: Tissue(1.09, 1.63, 0.53, 0.51, 0.0),  # brain ("fake")
    10: Tissue(0.54, 0.8, 0.5, 0.35, 0.0),  # spinal cord
    11: Tissue(0.2, 1.06, 0.49, 0.4, 0.0),  # liver
    12: Tissue(1.09, 1.63, 0.43, 0.41, 0.0),  # generic soft tissue
    13: Tissue(7.8, 90.0, 0.78, 0.56, 0.1),  # bone
    14: Tissue(0.2, 1.63, 0.53, 0.5, 0.0),  # skull ("fake")
    15: Tissue(0.5, 1.06, 0.9, 0.65, 0.24),  # vessel / blood
}


def _ranges(*pairs: tuple[range | list[int] | int, object]) -> dict[int, object]:
    out: dict[int, object] = {}
    for ids, value in pairs:
        for i in [ids] if isinstance(ids, int) else ids:
            out[i] = value
    return out


#: Label id -> reference tissue id (the intended label_conversion.yaml + project ids).
REFERENCE_LABEL_TISSUE: dict[int, int] = _ranges(
    (0, 0),
    (1, 12),  # spleen
    ([2, 3], 6),  # kidneys
    (4, 12),  # gallbladder
    (5, 11),  # liver
    (range(6, 10), 12),  # stomach, pancreas, adrenal glands
    (range(10, 15), 2),  # lung lobes
    (range(15, 23), 12),  # esophagus ... prostate
    ([23, 24], 6),  # kidney cysts
    (range(25, 51), 13),  # sacrum, vertebrae S1 ... C1
    (51, 8),  # heart
    (range(52, 69), 15),  # vessels
    (range(69, 79), 13),  # humerus ... hips
    (79, 10),  # spinal cord
    (range(80, 90), 8),  # gluteal, autochthon, iliopsoas muscles
    (90, 9),  # brain
    (91, 14),  # skull
    (range(92, 118), 13),  # ribs, sternum, costal cartilages
    ([118, 119, 120], 12),  # skin, subcutaneous fat, body_trunc
    (121, 12),  # intervertebral discs (inside the reference's body label)
    (122, 10),  # spinal canal
    ([123, 124], 12),  # spinal ligaments, thoracolumbar fascia (no ligament tissue there)
    (GEL, 4),  # coupling gel: water
)
REFERENCE_DEFAULT_TISSUE = 12

# ----------------------------------------------------------------------------- physical
#: Physical tissue classes. impedance MRayl, alpha dB/cm/MHz, hu Hounsfield units.
PHYSICAL_TISSUES: dict[str, Tissue] = {
    # Z [B]; alpha [B] (air attenuation is huge at MHz; transmission into air is ~0 anyway).
    "air": Tissue(alpha=1.64, impedance=0.0004, mu0=0.0, mu1=0.0, sigma0=0.0, hu=-1000.0),
    # coupling gel ~ water [S]/[D]: anechoic
    "gel": Tissue(alpha=0.002, impedance=1.49, mu0=0.0, mu1=0.0, sigma0=0.0, hu=0.0),
    # Z [B], alpha [B]; echogenic dermis [R]
    "skin": Tissue(alpha=1.0, impedance=1.99, mu0=0.7, mu1=2.0, sigma0=0.05, hu=30.0),
    # Z, alpha 0.63 [D]/[B]; hypoechoic [R]
    "fat": Tissue(alpha=0.63, impedance=1.38, mu0=0.35, mu1=2.0, sigma0=0.05, hu=-100.0),
    # Z 1.68 [S]; alpha 0.96 across the fibres [D] (posterior beams cross the paraspinal fibres)
    "muscle": Tissue(alpha=0.96, impedance=1.68, mu0=0.3, mu1=2.0, sigma0=0.05, hu=50.0),
    # generic trunk soft tissue: Z 1.63 [I]/[B]; alpha 0.6 (between liver 0.5 and fat 0.63) [R]
    "soft_tissue": Tissue(alpha=0.6, impedance=1.63, mu0=0.5, mu1=2.0, sigma0=0.05, hu=40.0),
    "liver": Tissue(alpha=0.5, impedance=1.65, mu0=0.5, mu1=2.0, sigma0=0.05, hu=55.0),  # [D]
    "kidney": Tissue(alpha=1.0, impedance=1.62, mu0=0.4, mu1=2.0, sigma0=0.05, hu=30.0),  # [D]
    # blood: Z 1.61 [B], alpha 0.18 [B]; nearly anechoic (Burger mu0 0.001)
    "blood": Tissue(alpha=0.18, impedance=1.61, mu0=0.03, mu1=0.0, sigma0=0.0, hu=40.0),
    # CSF / urine / bile / cyst fluid: Z 1.52, alpha 0.002 [I]; anechoic
    "fluid": Tissue(alpha=0.002, impedance=1.52, mu0=0.02, mu1=0.0, sigma0=0.0, hu=10.0),
    # aerated lung: Z ~0.1-0.4 [I], alpha 40 [D]
    "lung": Tissue(alpha=40.0, impedance=0.26, mu0=0.5, mu1=2.0, sigma0=0.1, hu=-800.0),
    # cortical bone: Z 6.1-7.8 [S]/[B] (6.5 at 1200 HU; CT refinement gives ~7.6 at 1600 HU),
    # alpha 1-20 [S]/[D] -> 10; strongly scattering (shadowed anyway)
    "bone": Tissue(alpha=10.0, impedance=6.5, mu0=0.8, mu1=2.0, sigma0=0.2, hu=1200.0),
    # dense fibrous tissue (spinal ligaments, thoracolumbar fascia): brighter than muscle, its
    # collagen fibres scatter strongly [R]; Z 1.70 (tendon-like) and alpha 2 (tendon ~1.5-4)
    # [R], hu 75 (phantom's ligament CT)
    "ligament": Tissue(alpha=2.0, impedance=1.70, mu0=0.75, mu1=2.0, sigma0=0.1, hu=75.0),
    # cartilage (costal cartilage, intervertebral disc): Z ~1.7 [C], alpha ~1.5 [R]
    "cartilage": Tissue(alpha=1.5, impedance=1.7, mu0=0.3, mu1=2.0, sigma0=0.05, hu=90.0),
    # spinal cord / nerve: soft-tissue-like, hypoechoic [R]
    "nerve": Tissue(alpha=0.6, impedance=1.63, mu0=0.2, mu1=1.0, sigma0=0.0, hu=35.0),
    "brain": Tissue(alpha=0.6, impedance=1.6, mu0=0.3, mu1=2.0, sigma0=0.0, hu=35.0),  # [R]
}

#: Label id -> physical tissue class.
PHYSICAL_LABEL_TISSUE: dict[int, str] = _ranges(
    (0, "air"),
    (1, "soft_tissue"),  # spleen
    ([2, 3], "kidney"),
    (4, "fluid"),  # gallbladder (bile)
    (5, "liver"),
    (range(6, 10), "soft_tissue"),  # stomach, pancreas, adrenal glands
    (range(10, 15), "lung"),
    (15, "soft_tissue"),  # esophagus
    (16, "lung"),  # trachea: air-filled
    (range(17, 21), "soft_tissue"),  # thyroid, small bowel, duodenum, colon
    (21, "fluid"),  # urinary bladder
    (22, "soft_tissue"),  # prostate
    ([23, 24], "fluid"),  # kidney cysts
    (range(25, 51), "bone"),  # sacrum, vertebrae
    (51, "muscle"),  # heart
    (range(52, 69), "blood"),  # vessels
    (range(69, 79), "bone"),  # limb and girdle bones
    (79, "nerve"),  # spinal cord
    (range(80, 90), "muscle"),
    (90, "brain"),
    (91, "bone"),  # skull
    (range(92, 117), "bone"),  # ribs, sternum
    (117, "cartilage"),  # costal cartilages
    (118, "skin"),
    (119, "fat"),
    (120, "soft_tissue"),  # body_trunc
    (121, "cartilage"),  # intervertebral discs
    (122, "fluid"),  # spinal canal: CSF around the cauda equina
    ([123, 124], "ligament"),  # spinal ligaments, thoracolumbar fascia
    (GEL, "gel"),
)
PHYSICAL_DEFAULT_TISSUE = "soft_tissue"

#: CT -> impedance curve m(HU), piecewise linear through (HU, MRayl) anchors from the table
#: above (air, fat, water, soft tissue, cartilage, cancellous bone [C] 1.5-3.5, cortical bone);
#: constant beyond the ends. Tissues on the curve (Z_tissue = m(hu)) change impedance only
#: with the CT, so a partial-volume ramp carries an interface's impedance jump smoothly; those
#: off it (skin) keep their literature contrast on top.
HU_IMPEDANCE: tuple[tuple[float, float], ...] = (
    (-1000.0, 0.0004),
    (-100.0, 1.38),
    (0.0, 1.49),
    (40.0, 1.63),
    (90.0, 1.70),
    (250.0, 2.5),
    (1200.0, 6.5),
    (2000.0, 7.8),
)


def impedance_of_hu(hu: torch.Tensor) -> torch.Tensor:
    """m(HU): impedance (MRayl) of CT values along ``HU_IMPEDANCE`` (float64)."""
    hu = torch.as_tensor(hu, dtype=torch.float64)
    xs = torch.tensor([a for a, _ in HU_IMPEDANCE], dtype=torch.float64)
    ys = torch.tensor([b for _, b in HU_IMPEDANCE], dtype=torch.float64)
    h = hu.clamp(xs[0], xs[-1])
    i = torch.searchsorted(xs, h, right=True).clamp(1, len(xs) - 1)
    x0, x1, y0, y1 = xs[i - 1], xs[i], ys[i - 1], ys[i]
    return y0 + (y1 - y0) * (h - x0) / (x1 - x0)


class TissueTable:
    """A model's label -> tissue map and tissue parameters, answered as per-label lookups.

    ``column(name)`` returns a (256,) float64 tensor indexed by label id, so a whole label slice
    is looked up with one gather (``torch.take(column, labels.long())``).
    """

    def __init__(
        self,
        label_tissue: dict[int, object],
        tissues: dict[object, Tissue],
        default: object,
        name: str = "",
    ) -> None:
        missing = {t for t in label_tissue.values() if t not in tissues} | (
            set() if default in tissues else {default}
        )
        if missing:
            raise KeyError(
                f"tissue table {name!r}: no parameters for tissues {sorted(map(str, missing))}"
            )
        bad = [i for i in label_tissue if not 0 <= int(i) <= 255]
        if bad:
            raise ValueError(f"tissue table {name!r}: label ids must be 0-255, got {bad}")
        self.name = name
        self.label_tissue = dict(label_tissue)
        self.tissues = dict(tissues)
        self.default = default

    def tissue_of(self, label: int) -> object:
        """The tissue key a label id maps to."""
        return self.label_tissue.get(int(label), self.default)

    def params(self, label: int) -> Tissue:
        return self.tissues[self.tissue_of(label)]

    def column(self, field: str) -> torch.Tensor:
        """(256,) float64 tensor: ``field`` of the tissue of every label id."""
        if field not in Tissue.__dataclass_fields__:
            raise KeyError(
                f"unknown tissue field {field!r}; one of {list(Tissue.__dataclass_fields__)}"
            )
        return torch.tensor(
            [getattr(self.params(i), field) for i in range(256)], dtype=torch.float64
        )


def reference_table() -> TissueTable:
    """The ``reference`` model's table (the reference's tissues, intended mapping)."""
    return TissueTable(
        REFERENCE_LABEL_TISSUE, REFERENCE_TISSUES, REFERENCE_DEFAULT_TISSUE, "reference"
    )


def physical_table() -> TissueTable:
    """The ``physical`` model's table (literature acoustics)."""
    return TissueTable(PHYSICAL_LABEL_TISSUE, PHYSICAL_TISSUES, PHYSICAL_DEFAULT_TISSUE, "physical")
