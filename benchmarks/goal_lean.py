"""How far the beam leans at the navigation goal, and whether a policy's final offset across
the spine follows it. The figures in docs/envs.md (``observe_tilt``) come from

    python benchmarks/goal_lean.py --patients 5-9 100-104 200-204 \
        tests/data/totalsegmentator_example --episodes DIR/episodes/*.npz

For each patient: the lean of the beam toward +x_P at {G} (the skin's smoothed inward normal
above the L4 body centroid, ``SkinSurface.surface_pose``), in degrees, and where on the skin
(x, z from {G}, mm; 0.5 mm grid over +-30 mm) the transverse view's beam passes nearest the
centroid instead: how far a goal "centred on the target" would lie from {G}; over the patients,
the mean and median of that distance (where a policy that centred the target perfectly would
end). Also which vertebra the transverse view at {G} shows (the level whose bone most of its
beams within +-20 mm across meet first, ``morphometry.first_bone_labels``, and on how many of
the 21) and how far along the spine (z from {G}, 2 mm steps over -30..+40 mm) the view whose
beams meet L4 first most often lies: the beam leans with the back's slope, so the view above
the centroid can show the arch below. With ``--episodes`` (logs ``sonogym eval`` wrote;
episode k ran on patient (k % num_envs) % P of its test env), also each patient's median final
x (mm, across the spine, from {G}) of the ``policy`` episodes that ended within 20 mm of {G}
along the spine (a level off is another error), and over the patients found in the logs the
correlation of that median with sin(lean) and the least-squares slope.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from sonogym.anatomy import labels as L
from sonogym.anatomy.morphometry import first_bone_labels
from sonogym.envs.options import parse_patients
from sonogym.envs.patients import TARGET, resolve_patients
from sonogym.evaluation.episodes import episode_patient, load_log

SPACING = 0.001  # m, the training phantoms' voxel size
BEAMS = np.arange(-20.0, 20.1, 2.0)  # mm, lateral offsets of the beams read per view
LEVEL_NAMES = {i: lv for lv, i in L.VERTEBRA_IDS.items()} | {L.LABEL_IDS["sacrum"]: "sacrum"}


def goal_views(patient) -> tuple[float, float, float]:
    """(sin of the beam's lean toward +x_P at {G}, and (x, z) mm from {G} of the transverse
    view whose beam passes nearest the target's centroid), from one grid of transverse views
    around {G} (0.5 mm steps within +-30 mm; {G} is its centre)."""
    c = patient.landmarks.vertebra(TARGET).centre
    g = torch.arange(-60, 61, dtype=torch.float64) * 0.5e-3
    gx, gz = (a.reshape(-1) for a in torch.meshgrid(g, g, indexing="ij"))
    pos, rot = patient.skin.surface_pose(gx + c[0], gz + c[2], torch.full_like(gx, math.pi))
    beam, v = rot[..., 2], torch.as_tensor(c) - pos
    miss = (v - (v * beam).sum(-1, keepdim=True) * beam).norm(dim=-1)
    j = int(miss.argmin())
    at_goal = len(gx) // 2  # the grid's centre: offset (0, 0)
    return float(beam[at_goal, 0]), float(gx[j]) * 1e3, float(gz[j]) * 1e3


def level_views(patient) -> tuple[str, int, float]:
    """(the level the transverse view at {G} shows, on how many of its ``BEAMS``, and the z (mm
    from {G}) of the view whose beams meet L4 first most often; nearest {G} on ties)."""
    c = patient.landmarks.vertebra(TARGET).centre
    l4 = L.VERTEBRA_IDS[TARGET]

    def first(dz: float) -> np.ndarray:
        return first_bone_labels(patient, c[0], c[2] + dz * 1e-3, math.pi, BEAMS)

    views = {dz: first(dz) for dz in sorted(np.arange(-30.0, 40.1, 2.0), key=abs)}  # {G} first
    ids, counts = np.unique(views[0.0], return_counts=True)
    shown = int(ids[counts.argmax()])
    best = max(views, key=lambda dz: int((views[dz] == l4).sum()))  # first max: nearest {G}
    return LEVEL_NAMES.get(shown, "none" if shown == 0 else str(shown)), int(counts.max()), best


def final_x_by_patient(paths: list[str]) -> dict[str, list[float]]:
    """{patient spec: final x (mm) of its in-level policy episodes} over the logs."""
    out: dict[str, list[float]] = {}
    for path in paths:
        log = load_log(path)
        end = log.tracks["policy"][:, -1]  # (trials, [x, z, yaw])
        for k, (x, z) in enumerate(end[:, :2]):
            if abs(z) < 20.0:
                out.setdefault(str(episode_patient(log, k)), []).append(float(x))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--patients", nargs="+", required=True, help="seeds, A-B ranges, folders")
    ap.add_argument("--episodes", nargs="*", default=[], help="episode logs of sonogym eval")
    args = ap.parse_args()
    specs = parse_patients(args.patients)
    ends = final_x_by_patient(args.episodes)
    pairs, centred, l4_views = [], [], []
    print(
        "| patient | lean to +x_P [deg] | centred goal x, z [mm] | {G} view shows "
        "| L4 view z [mm] | median final x [mm] | episodes |"
    )
    print("|---|---|---|---|---|---|---|")
    for spec, patient in zip(specs, resolve_patients(specs, SPACING), strict=True):
        s, cx, cz = goal_views(patient)
        centred.append(math.hypot(cx, cz))
        xs = ends.get(str(spec), [])
        med = float(np.median(xs)) if xs else float("nan")
        if xs:
            pairs.append((s, med))
        shown, n, l4z = level_views(patient)
        l4_views.append((shown, l4z))
        lean = math.degrees(math.asin(s))
        print(
            f"| {spec} | {lean:+.1f} | {cx:+.1f}, {cz:+.1f} | {shown} ({n}/{len(BEAMS)}) "
            f"| {l4z:+.0f} | {med:+.1f} | {len(xs)} |"
        )
    c = np.array(centred)
    print(
        f"\nthe centred view lies {np.mean(c):.1f} mm (mean; median {np.median(c):.1f}, "
        f"{c.min():.1f}-{c.max():.1f}) from {{G}} over the {len(c)} patients"
    )
    shows_l4 = sum(shown == TARGET for shown, _ in l4_views)
    zs = np.array([z for _, z in l4_views])
    print(
        f"the view at {{G}} shows {TARGET} in {shows_l4} of {len(zs)} patients; the view meeting "
        f"{TARGET} most lies {np.median(zs):+.0f} mm along the spine from {{G}} (median; "
        f"{zs.min():+.0f}..{zs.max():+.0f})"
    )
    if len(pairs) >= 3:
        a = np.array(pairs)
        r = np.corrcoef(a[:, 0], a[:, 1])[0, 1]
        slope = np.polyfit(a[:, 0], a[:, 1], 1)[0]
        print(f"\n{len(a)} patients: r = {r:+.2f}, median final x = {slope:+.1f} mm x sin(lean)")


if __name__ == "__main__":
    main()
