"""Patient models: CT + TotalSegmentator labels, the procedural phantom, skin and landmarks."""

from sonogym.anatomy.labels import LABEL_IDS, LABELS, label_id
from sonogym.anatomy.landmarks import LandmarkError, Landmarks, PedicleTrajectory, VertebraFrame
from sonogym.anatomy.patient import Patient, PatientError, PatientModel
from sonogym.anatomy.phantom import PhantomParams, cache_dir, load_phantom, make_phantom
from sonogym.anatomy.surface import SkinSurface
from sonogym.anatomy.totalseg import load_totalsegmentator, save_totalsegmentator

__all__ = [
    "LABELS",
    "LABEL_IDS",
    "LandmarkError",
    "Landmarks",
    "Patient",
    "PatientModel",
    "PatientError",
    "PedicleTrajectory",
    "PhantomParams",
    "SkinSurface",
    "VertebraFrame",
    "cache_dir",
    "label_id",
    "load_phantom",
    "load_totalsegmentator",
    "make_phantom",
    "save_totalsegmentator",
]
