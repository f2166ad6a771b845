"""The label table: TotalSegmentator v2 "total" ids, plus project ids >= 118.

Every label map in SonoGym uses these ids. Ids 1-117 are TotalSegmentator v2's ``total`` task
(never its v1 ids, which differ). Structures TotalSegmentator's ``total`` task lacks get project
ids from 118 on; their names are the file names TotalSegmentator's other tasks use where one
exists (``body_trunc`` from the ``body`` task, ``subcutaneous_fat`` from ``tissue_types``,
``intervertebral_discs`` from ``vertebrae_body``), so such masks load without renaming.
120 = body/trunk, as in the SonoGym reference implementation.

| id  | name                  | what                                                    |
|-----|-----------------------|---------------------------------------------------------|
| 0   | (background)          | outside the body: air                                   |
| 1-117 | TotalSegmentator v2 | see ``TOTALSEG_V2``                                     |
| 118 | skin                  | outer 2-3 mm of the body                                |
| 119 | subcutaneous_fat      | fat between skin and muscle fascia                      |
| 120 | body_trunc            | any other soft tissue of the trunk (reference's 120)    |
| 121 | intervertebral_discs  | annulus + nucleus                                       |
| 122 | spinal_canal          | CSF / cauda equina inside the vertebral canal           |
| 123 | spinal_ligaments      | supra- and interspinous ligaments, ligamentum flavum    |
| 124 | thoracolumbar_fascia  | fascia over the paraspinal (autochthon) muscles         |
"""

from __future__ import annotations

_RIBS_LEFT = {91 + i: f"rib_left_{i}" for i in range(1, 13)}
_RIBS_RIGHT = {103 + i: f"rib_right_{i}" for i in range(1, 13)}
_THORACIC = {32 + (12 - i): f"vertebrae_T{i}" for i in range(1, 13)}
_CERVICAL = {43 + (8 - i): f"vertebrae_C{i}" for i in range(1, 8)}

#: TotalSegmentator v2 ``total`` task: id -> class name.
TOTALSEG_V2: dict[int, str] = {
    1: "spleen",
    2: "kidney_right",
    3: "kidney_left",
    4: "gallbladder",
    5: "liver",
    6: "stomach",
    7: "pancreas",
    8: "adrenal_gland_right",
    9: "adrenal_gland_left",
    10: "lung_upper_lobe_left",
    11: "lung_lower_lobe_left",
    12: "lung_upper_lobe_right",
    13: "lung_middle_lobe_right",
    14: "lung_lower_lobe_right",
    15: "esophagus",
    16: "trachea",
    17: "thyroid_gland",
    18: "small_bowel",
    19: "duodenum",
    20: "colon",
    21: "urinary_bladder",
    22: "prostate",
    23: "kidney_cyst_left",
    24: "kidney_cyst_right",
    25: "sacrum",
    26: "vertebrae_S1",
    27: "vertebrae_L5",
    28: "vertebrae_L4",
    29: "vertebrae_L3",
    30: "vertebrae_L2",
    31: "vertebrae_L1",
    **_THORACIC,
    **_CERVICAL,
    51: "heart",
    52: "aorta",
    53: "pulmonary_vein",
    54: "brachiocephalic_trunk",
    55: "subclavian_artery_right",
    56: "subclavian_artery_left",
    57: "common_carotid_artery_right",
    58: "common_carotid_artery_left",
    59: "brachiocephalic_vein_left",
    60: "brachiocephalic_vein_right",
    61: "atrial_appendage_left",
    62: "superior_vena_cava",
    63: "inferior_vena_cava",
    64: "portal_vein_and_splenic_vein",
    65: "iliac_artery_left",
    66: "iliac_artery_right",
    67: "iliac_vena_left",
    68: "iliac_vena_right",
    69: "humerus_left",
    70: "humerus_right",
    71: "scapula_left",
    72: "scapula_right",
    73: "clavicula_left",
    74: "clavicula_right",
    75: "femur_left",
    76: "femur_right",
    77: "hip_left",
    78: "hip_right",
    79: "spinal_cord",
    80: "gluteus_maximus_left",
    81: "gluteus_maximus_right",
    82: "gluteus_medius_left",
    83: "gluteus_medius_right",
    84: "gluteus_minimus_left",
    85: "gluteus_minimus_right",
    86: "autochthon_left",
    87: "autochthon_right",
    88: "iliopsoas_left",
    89: "iliopsoas_right",
    90: "brain",
    91: "skull",
    **_RIBS_LEFT,
    **_RIBS_RIGHT,
    116: "sternum",
    117: "costal_cartilages",
}

#: Project ids for what TotalSegmentator's ``total`` task lacks.
PROJECT_LABELS: dict[int, str] = {
    118: "skin",
    119: "subcutaneous_fat",
    120: "body_trunc",
    121: "intervertebral_discs",
    122: "spinal_canal",
    123: "spinal_ligaments",
    124: "thoracolumbar_fascia",
}

#: Every id the patient model uses -> name (background 0 excluded).
LABELS: dict[int, str] = {**TOTALSEG_V2, **PROJECT_LABELS}
#: name -> id.
LABEL_IDS: dict[str, int] = {name: i for i, name in LABELS.items()}

SKIN = 118
SUBCUTANEOUS_FAT = 119
BODY_TRUNC = 120
INTERVERTEBRAL_DISCS = 121
SPINAL_CANAL = 122
SPINAL_LIGAMENTS = 123
THORACOLUMBAR_FASCIA = 124

#: Lumbar vertebrae, cranial to caudal, with their TotalSegmentator v2 ids.
LUMBAR_VERTEBRAE: dict[str, int] = {"L1": 31, "L2": 30, "L3": 29, "L4": 28, "L5": 27}
#: Vertebra level name ("T12", "L4", "S1", ...) -> TotalSegmentator v2 id.
VERTEBRA_IDS: dict[str, int] = {
    name.removeprefix("vertebrae_"): i for i, name in TOTALSEG_V2.items() if "vertebrae_" in name
}
#: Every bone id (vertebrae, sacrum, pelvis, limbs, ribs, sternum, skull).
BONE_IDS: frozenset[int] = frozenset([25, *range(26, 51), *range(69, 79), 91, *range(92, 117)])


def label_id(name_or_id: str | int) -> int:
    """Id for a class name ("vertebrae_L4", "L4", "skin") or an id; raises with the known names."""
    if isinstance(name_or_id, int):
        if name_or_id not in LABELS:
            raise KeyError(
                f"unknown label id {name_or_id}; ids are 1-{max(LABELS)} "
                "(see sonogym.anatomy.labels)"
            )
        return name_or_id
    if name_or_id in LABEL_IDS:
        return LABEL_IDS[name_or_id]
    if name_or_id in VERTEBRA_IDS:
        return VERTEBRA_IDS[name_or_id]
    raise KeyError(
        f"unknown label name {name_or_id!r}; use a TotalSegmentator v2 class name such as "
        f"'vertebrae_L4', a level such as 'L4', or one of {sorted(PROJECT_LABELS.values())}"
    )
