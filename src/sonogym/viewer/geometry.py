"""What the viewer draws, as plain arrays in the patient frame {P} (metres): surface meshes of a
label map, the probe's image planes, an arm's joint origins and reconstructed bone points.
Nothing here knows about Rerun (``sonogym.viewer.draw`` logs these arrays)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from sonogym.anatomy.labels import BONE_IDS, VERTEBRA_IDS
from sonogym.ultrasound.probe import ProbeGeometry

#: m, sampling of the surfaces: the skin is smooth and large, bone needs finer detail.
SKIN_RESOLUTION = 0.003
BONE_RESOLUTION = 0.002


@dataclass(frozen=True)
class SurfaceMesh:
    """A triangle mesh: ``vertices`` (V, 3) float32 in {P} (m), ``faces`` (F, 3) uint32,
    ``normals`` (V, 3) float32 unit vectors pointing out of the structure."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray


def mask_surface(
    name: str, mask: np.ndarray, affine: np.ndarray, resolution: float
) -> SurfaceMesh | None:
    """Marching cubes of a boolean voxel ``mask`` on the axis-aligned grid ``affine`` (voxel
    index -> {P}, m), decimated to blocks of about ``resolution`` metres: the 0.5 iso-surface
    of the fraction of each block inside the mask (a partial-volume field, so the surface is
    smooth where a binary one would show voxel steps). The field is padded by one empty block,
    so structures cut by the volume's border are closed. None for an empty mask."""
    from skimage.measure import marching_cubes

    if not mask.any():
        return None
    spacing = np.diag(affine)[:3]
    s = max(1, round(resolution / float(spacing.min())))
    m = np.pad(mask, [(0, (-n) % s) for n in mask.shape])
    x, y, z = (n // s for n in m.shape)
    frac = m.reshape(x, s, y, s, z, s).sum(axis=(1, 3, 5), dtype=np.uint16) / np.float32(s**3)
    verts, faces, normals, _ = marching_cubes(np.pad(frac, 1), 0.5)
    # block i (after the pad: i + 1) is centred on voxel i * s + (s - 1) / 2
    verts = ((verts - 1) * s + (s - 1) / 2) * spacing + affine[:3, 3]
    # its normals point out of the mask; its triangles wind clockwise seen from outside:
    # reversed, they wind counter-clockwise, the front-face convention of renderers
    return SurfaceMesh(
        name,
        verts.astype(np.float32),
        np.ascontiguousarray(faces[:, ::-1]).astype(np.uint32),
        normals.astype(np.float32),
    )


def patient_surfaces(labels: np.ndarray, affine: np.ndarray, target: str) -> list[SurfaceMesh]:
    """The skin (the body's outer surface), the bones other than the ``target`` vertebra, and
    the target vertebra, as decimated meshes (``SKIN_RESOLUTION``, ``BONE_RESOLUTION``)."""
    target_id = VERTEBRA_IDS[target]
    bone = np.isin(labels, np.array(sorted(BONE_IDS - {target_id}), dtype=labels.dtype))
    parts = [
        mask_surface("skin", labels > 0, affine, SKIN_RESOLUTION),
        mask_surface("bone", bone, affine, BONE_RESOLUTION),
        mask_surface(target, labels == target_id, affine, BONE_RESOLUTION),
    ]
    return [p for p in parts if p is not None]


@dataclass(frozen=True)
class ImageQuad:
    """One image slice as a rectangle in the probe frame {U}: ``vertices`` (4, 3) m (corners of
    the pixel grid's outer edges: row 0 at the probe face), ``texcoords`` (4, 2) with (0, 0)
    the image's top-left pixel (row 0, column 0) and (1, 1) its bottom-right, ``faces`` (2, 3)."""

    vertices: np.ndarray
    texcoords: np.ndarray
    faces: np.ndarray


def image_quads(probe: ProbeGeometry) -> list[ImageQuad]:
    """One quad per elevation slice of ``probe``'s images, where its pixels lie in {U}:
    columns along x_U, rows along z_U (depth), the slice at its elevation y_U
    (``ProbeGeometry``'s pixel convention, pixel centres half a pixel inside the edges)."""
    x = probe.lateral_positions().numpy()
    z = probe.depth_positions().numpy()
    x0, x1 = x[0] - probe.width_spacing / 2, x[-1] + probe.width_spacing / 2
    z0, z1 = z[0] - probe.depth_spacing / 2, z[-1] + probe.depth_spacing / 2
    tex = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    out = []
    for y in probe.elevation_positions().numpy():
        v = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], np.float32)
        out.append(ImageQuad(v, tex, faces))
    return out


def arm_joint_origins(arm, q: torch.Tensor, env: int = 0) -> np.ndarray:
    """(F, 3) origins of every frame of arm ``env`` at joints ``q`` (its (7,) row), base to
    tool tip, in {P} (m): a polyline through them draws the arm's links."""
    ids = torch.tensor([env], device=q.device)
    order = sorted(arm.chain.frame_to_idx.items(), key=lambda kv: kv[1])
    pts = [arm.fk(q[env : env + 1], link=name, env_ids=ids)[0][0] for name, _ in order]
    pts = torch.stack(pts).double().cpu().numpy()
    keep = np.ones(len(pts), bool)
    keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6  # frames at one origin
    return pts[keep]


def voxel_centres(volume: torch.Tensor, corner: np.ndarray, voxel: float) -> np.ndarray:
    """(K, 3) centres in {P} (m) of the set voxels of a boolean ``volume`` (S, S, S) whose
    voxel (0, 0, 0) starts at ``corner`` (3,) with edge ``voxel`` (m)."""
    idx = torch.nonzero(volume).cpu().numpy()
    return (np.asarray(corner, np.float64) + (idx + 0.5) * voxel).astype(np.float32)


def to_frame(pos: np.ndarray, rot: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (K, 3) given in a frame with origin ``pos`` (3,) and axes ``rot`` (3, 3) (columns)
    -> {P}."""
    return np.asarray(points) @ np.asarray(rot).T + np.asarray(pos)
