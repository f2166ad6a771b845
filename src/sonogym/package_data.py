"""Data that ships inside the package, found through ``importlib.resources``: the same path in
a checkout and in an installed package.

The real TotalSegmentator subject (``sonogym/data/totalsegmentator_example``: a 3 mm CT and
its masks, ~7 MB, Apache-2.0) is what ``sonogym morphometry`` compares the phantoms with and
what the population recipe of ``sonogym reproduce`` evaluates on. Recipes and docs name it by
its checkout path, ``tests/data/totalsegmentator_example``; ``data_path`` turns that name (or
the bare ``totalsegmentator_example``) into the package's copy wherever the path itself does
not exist, e.g. outside a checkout.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

#: The real subject's folder name inside the package's ``data/``.
EXAMPLE_SUBJECT = "totalsegmentator_example"
#: Names that mean the shipped subject where no such path exists: its checkout path, as the
#: recipes and docs write it, and its bare name.
EXAMPLE_SUBJECT_NAMES = (Path("tests/data") / EXAMPLE_SUBJECT, Path(EXAMPLE_SUBJECT))


def example_subject() -> Path:
    """The folder of the real subject that ships with sonogym (ct.nii.gz + segmentations/)."""
    return Path(str(importlib.resources.files("sonogym") / "data" / EXAMPLE_SUBJECT))


def data_path(given: str | Path) -> str | Path:
    """``given`` itself when it exists (or names anything but the shipped subject); the
    package's copy of the subject when ``given`` names it (``EXAMPLE_SUBJECT_NAMES``) and no
    such path exists here. The type of ``given`` is kept."""
    path = Path(given)
    if path.exists() or path not in EXAMPLE_SUBJECT_NAMES:
        return given
    return str(example_subject()) if isinstance(given, str) else example_subject()
