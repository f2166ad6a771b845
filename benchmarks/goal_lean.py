"""How far the beam leans at the navigation goal, and whether a policy's final offset across
the spine follows it. The figures in docs/envs.md (``observe_tilt``) come from

    python benchmarks/goal_lean.py --patients 5-9 100-104 200-204 \
        tests/data/totalsegmentator_example --episodes DIR/episodes/*.npz

For each patient: the lean of the beam toward +x_P at {G} (the skin's smoothed inward normal
above the L4 body centroid, ``SkinSurface.surface_pose``), in degrees, and where on the skin
(x, z from {G}, mm; 0.5 mm grid over +-30 mm) the transverse view's beam passes nearest the
centroid instead: how far a goal "centred on the target" would lie from {G}; over the patients,
the mean and median of that distance (where a policy that centred the target perfectly would
end). With ``--episodes`` (logs ``sonogym eval`` wrote; episode k ran on patient
(k % num_envs) % P of its test env), also each patient's median final x (mm, across the spine,
from {G}) of the ``policy`` episodes that ended within 20 mm of {G} along the spine (a level off
is another error), and over the patients found in the logs the correlation of that median with
sin(lean) and the least-squares slope.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from sonogym.envs.options import parse_patients
from sonogym.envs.patients import TARGET, resolve_patients
from sonogym.evaluation.episodes import episode_patient, load_log

SPACING = 0.001  # m, the training phantoms' voxel size


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
    pairs, centred = [], []
    print(
        "| patient | lean to +x_P [deg] | centred goal x, z [mm] | median final x [mm] | episodes |"
    )
    print("|---|---|---|---|---|")
    for spec, patient in zip(specs, resolve_patients(specs, SPACING), strict=True):
        s, cx, cz = goal_views(patient)
        centred.append(math.hypot(cx, cz))
        xs = ends.get(str(spec), [])
        med = float(np.median(xs)) if xs else float("nan")
        if xs:
            pairs.append((s, med))
        lean = math.degrees(math.asin(s))
        print(f"| {spec} | {lean:+.1f} | {cx:+.1f}, {cz:+.1f} | {med:+.1f} | {len(xs)} |")
    c = np.array(centred)
    print(
        f"\nthe centred view lies {np.mean(c):.1f} mm (mean; median {np.median(c):.1f}, "
        f"{c.min():.1f}-{c.max():.1f}) from {{G}} over the {len(c)} patients"
    )
    if len(pairs) >= 3:
        a = np.array(pairs)
        r = np.corrcoef(a[:, 0], a[:, 1])[0, 1]
        slope = np.polyfit(a[:, 0], a[:, 1], 1)[0]
        print(f"\n{len(a)} patients: r = {r:+.2f}, median final x = {slope:+.1f} mm x sin(lean)")


if __name__ == "__main__":
    main()
