"""Render ultrasound images of a patient at surface poses, to arrays and PNG files.

The ``sonogym image`` command is a thin wrapper over :func:`render_command`. A surface pose is
(x, z, yaw[, tilt]) on the back (``SkinSurface.surface_pose``): x and z in the patient frame {P}
(x toward the patient's right, z superior), yaw the angle of the probe's lateral axis in the
frontal plane from +x toward +z (pi: transverse image, pi/2: sagittal image), tilt about the
probe's lateral axis.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sonogym.anatomy.patient import Patient
from sonogym.ultrasound.probe import ProbeGeometry
from sonogym.ultrasound.registry import SimulatorOptions, get_simulator
from sonogym.ultrasound.simulator import US_MODELS
from sonogym.ultrasound.slicer import Slicer, Slices

#: Surface pose: x (m), z (m), yaw (rad), tilt (rad).
Pose = tuple[float, float, float, float]
PROBES = {"linear": ProbeGeometry.linear_2d, "volume": ProbeGeometry.volume_3d}


def parse_pose(text: str) -> Pose:
    """'x,z,yaw[,tilt]' with x, z in millimetres and yaw, tilt in radians -> SI pose."""
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (3, 4) or not all(math.isfinite(v) for v in vals):
        raise ValueError(
            f"bad pose {text!r}: expected 'x,z,yaw[,tilt]' (x, z in mm; yaw, tilt in rad), "
            "e.g. '0,10,3.1416' or '5,0,1.5708,0.2'"
        )
    x, z, yaw = vals[:3]
    tilt = vals[3] if len(vals) == 4 else 0.0
    return x * 1e-3, z * 1e-3, yaw, tilt


def default_poses(patient: Patient, level: str = "L4") -> list[Pose]:
    """Transverse and sagittal poses above a vertebra's body centre (or the middle of the
    back's surface if the vertebra is missing)."""
    from sonogym.anatomy import LandmarkError

    try:
        c = patient.landmarks.vertebra(level).centre
        x, z = float(c[0]), float(c[2])
    except LandmarkError:  # no such vertebra (or none at all): the middle of the back
        (x0, x1), (z0, z1) = patient.skin.x_range(), patient.skin.z_range()
        x, z = (x0 + x1) / 2, (z0 + z1) / 2
    return [(x, z, math.pi, 0.0), (x, z, math.pi / 2, 0.0)]


@dataclass(frozen=True)
class Rendering:
    """Slices and images of N poses: images[model] is (N, E, H, W) in [0, 1] for display."""

    poses: list[Pose]
    slices: Slices
    images: dict[str, torch.Tensor]


def render(
    patient: Patient,
    poses: Sequence[Pose],
    us_models: Sequence[str] = ("physical",),
    probe: ProbeGeometry | None = None,
) -> Rendering:
    """Slice and simulate ``poses`` (surface poses in SI) with each simulator of
    ``us_models`` (registered names: ``physical``, ``reference``, ...), keyed by its name.

    Display images as each simulator's registry entry views them (``SimulatorSpec.view``):
    ``physical`` as simulated; ``reference`` as raw / 20 clipped to [0, 1]."""
    if not poses:
        raise ValueError("render needs at least one pose")
    specs = [get_simulator(m) for m in us_models]  # unknown names fail before any work
    t = torch.tensor(poses, dtype=torch.float64)
    pos, rot = patient.skin.surface_pose(t[:, 0], t[:, 1], t[:, 2], t[:, 3])
    slices = Slicer(patient, probe)(pos.double(), rot.double())
    images = {}
    for spec in specs:
        sim = spec.build([patient], torch.device("cpu"), SimulatorOptions())
        images[spec.name] = spec.view(sim, slices)
    return Rendering(list(poses), slices, images)


def _tile(vol: np.ndarray) -> np.ndarray:
    """(E, H, W) -> (H, E * W + gaps): elevation slices side by side."""
    e, h, w = vol.shape
    if e == 1:
        return vol[0]
    out = np.full((h, e * w + (e - 1) * 2), np.nan, dtype=np.float32)
    for k in range(e):
        out[:, k * (w + 2) : k * (w + 2) + w] = vol[k]
    return out


def save_png(image: torch.Tensor | np.ndarray, path: str | Path, scale: int = 1) -> Path:
    """Write an (H, W) or (E, H, W) image in [0, 1] as an 8-bit grayscale PNG, each pixel
    repeated ``scale`` times in both directions."""
    import matplotlib.image

    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3:
        img = _tile(img)
    if scale > 1:
        img = img.repeat(scale, 0).repeat(scale, 1)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    matplotlib.image.imsave(path, np.nan_to_num(img, nan=0.0), cmap="gray", vmin=0.0, vmax=1.0)
    return path


def save_sheet(rendering: Rendering, path: str | Path, title: str = "") -> Path:
    """CT slice | label slice | US (one column per ultrasound model) for every pose, like the
    paper's Fig. 4."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = rendering.slices
    names = list(rendering.images)
    n = s.num_envs
    ncol = 2 + len(names)
    e, h, w = s.ct.shape[1:]
    aspect = (h * s.probe.depth_spacing) / (w * s.probe.width_spacing * (e if e > 1 else 1))
    fig, axes = plt.subplots(n, ncol, figsize=(3.2 * ncol, 3.4 * aspect * n + 0.6), squeeze=False)
    extent = (
        -w * s.probe.width_spacing * 500,
        w * s.probe.width_spacing * 500,
        h * s.probe.depth_spacing * 1e3,
        0,
    )
    for i in range(n):
        x, z, yaw, tilt = rendering.poses[i]
        panels = [
            ("CT (HU)", _tile(s.ct[i].numpy()), dict(cmap="gray", vmin=-400, vmax=1400)),
            (
                "labels",
                _tile(s.labels[i].numpy().astype(np.float32)),
                dict(cmap="tab20", vmin=0, vmax=122, interpolation="nearest"),
            ),
        ]
        panels += [
            (f"US: {k}", _tile(rendering.images[k][i].numpy()), dict(cmap="gray", vmin=0, vmax=1))
            for k in names
        ]
        for j, (label, img, kw) in enumerate(panels):
            ax = axes[i, j]
            ax.imshow(img, extent=extent, aspect="equal", **kw)
            ax.set_title(label if i == 0 else "", fontsize=10)
            if j == 0:
                ax.set_ylabel(
                    f"x {x * 1e3:.0f} mm, z {z * 1e3:.0f} mm\nyaw {yaw:.2f}, tilt {tilt:.2f} rad\n"
                    "depth (mm)",
                    fontsize=8,
                )
            else:
                ax.set_yticks([])
            ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def render_command(
    patient: Patient,
    poses: Sequence[Pose] | None = None,
    us_model: str = "physical",
    sheet: bool = False,
    probe: str = "linear",
    out: str | Path = "runs/image",
) -> list[Path]:
    """What ``sonogym image`` does: render and write PNGs; returns the written paths.

    us_model: a simulator name ("physical", "reference") or "both" (the two model-based
    models); probe: "linear" or "volume" (the five elevation
    slices side by side); out: a folder (per-pose PNGs, or sheet.png with ``sheet``)."""
    models = sorted(US_MODELS) if us_model == "both" else [get_simulator(us_model).name]
    if probe not in PROBES:
        raise ValueError(f"unknown probe {probe!r}; known probes: {sorted(PROBES)}")
    poses = list(poses) if poses else default_poses(patient)
    r = render(patient, poses, models, PROBES[probe]())
    out = Path(out)
    if sheet:
        title = f"{patient.name}: {', '.join(models)} model, {probe} probe"
        return [save_sheet(r, out / "sheet.png", title)]
    paths = []
    scale = max(1, round(r.slices.probe.depth_spacing / 0.5e-3))  # show pixels at ~0.5 mm
    for name, imgs in r.images.items():
        for i in range(len(poses)):
            paths.append(save_png(imgs[i].numpy(), out / f"us_{i}_{name}.png", scale))
    return paths
